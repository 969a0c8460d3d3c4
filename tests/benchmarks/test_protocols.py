"""Each row in the protocol of the number it is compared with: the paper's schedules, C3DPO's inputs and
evaluation, detection scores, and real data by default."""

import argparse
import json

import numpy as np
import pytest

from benchmarks import methods, table1
from benchmarks.common import choose_data
from benchmarks.registry import NotRun, RunContext, Split, schedule
from nrsfm.datasets.synthetic import human_sequences
from nrsfm.errors import ValidationError
from nrsfm.sequence import Sequence


@pytest.mark.parametrize("iterations", [14_000, 70_000, 100_000, 120_000])
def test_lr_falls_by_0_8_every_5000_iterations_at_the_papers_counts(iterations):
    cfg = schedule(iterations)
    assert cfg.iterations == iterations and cfg.lr_step == 5000
    boundary = cfg.phase_boundary  # batch-norm statistics freeze and the schedule restarts (authors' code)
    assert boundary == round(0.7 * iterations)
    for it in range(0, iterations, 250):
        local = it if it < boundary else it - boundary
        assert cfg.lr_at(it) == pytest.approx(1e-4 * 0.8 ** (local // 5000), rel=1e-12), it
    # each step lands on a multiple of 5,000 iterations of its phase, whatever the count
    for k in range(1, (boundary - 1) // 5000 + 1):
        assert cfg.lr_at(5000 * k) == pytest.approx(0.8 * cfg.lr_at(5000 * k - 1))
    # a compressed schedule only when asked for: the step scales with the count
    assert schedule(8000, compress=True).lr_step == round(5000 * 8000 / 70_000)
    assert schedule(8000).lr_step == 5000


def _h36m_like(frames: int = 6, subject: str = "S9", action: str = "Walking") -> Sequence:
    """A Human3.6M-named stand-in sequence (the ``Hip`` joint first)."""
    seq = human_sequences((subject,), ("walking",), (1,), n_frames=frames)[0]
    return seq.replace(meta={**seq.meta, "action": action})


def test_hip_frame_is_kudos_per_frame_scale():
    pts = np.array([[[0.0, 0.0], [3.0, 4.0], [0.0, 2.0], [9.0, 9.0]]])  # hip, two joints, one hidden
    w = np.array([[1.0, 1.0, 1.0, 0.0]])
    centre, scale = methods.hip_frame(pts, w, root=0)
    np.testing.assert_allclose(centre, [[[0.0, 0.0]]])
    assert scale == pytest.approx((5.0 + 2.0) / 2)  # the mean distance of the other visible joints to the hip
    w_no_hip = np.array([[0.0, 1.0, 1.0, 0.0]])  # a hidden hip: the visible points' mean stands in
    centre, scale = methods.hip_frame(pts, w_no_hip, root=0)
    np.testing.assert_allclose(centre, [[[1.5, 3.0]]])
    assert scale == pytest.approx(np.hypot(1.5, 1.0))


def _in_prn_units(pred_mm: np.ndarray, truth: Sequence) -> np.ndarray:
    """`(F, P, 3)` shapes in the ground truth's units turned into PRN's per-frame units (the inverse of
    :func:`prn.data.denormalize`)."""
    from prn.data import normalize_3d

    return pred_mm / normalize_3d(truth.points_3d)[1][:, None, None]


def test_c3dpo_hip_inputs_and_millimetres_follow_the_authors(monkeypatch):
    seq = _h36m_like()
    assert methods.root_joint(seq) == 0
    x, w, scale = methods.c3dpo_inputs([seq], 1.0, "hip")
    np.testing.assert_allclose(x[:, 0], 0.0, atol=1e-12)  # centred on the hip
    np.testing.assert_allclose(np.linalg.norm(x[:, 1:], axis=2).mean(axis=1), 1.0)  # unit mean hip distance
    np.testing.assert_allclose(x * scale[:, None, None] + seq.points_2d[:, :1], seq.points_2d, atol=1e-9)

    import baselines.c3dpo

    truth = seq.points_3d
    depth = (truth[..., 2] - truth[:, :1, 2]) / scale[:, None]

    def exact(model, xx, ww, replace_keypoints_with_input=True):  # the input's xy and the true depth, in its units
        return np.concatenate([xx, depth[..., None]], axis=2)

    monkeypatch.setattr(baselines.c3dpo, "predict_c3dpo", exact)
    preds = methods.c3dpo_test_predictions(None, Split([seq], [seq], [seq], [seq], "gt-ortho"), 1.0, "hip")
    # orthographic input: the 3D's hip scale is the 2D's, so the prediction is the hip-centred truth in millimetres
    hip_centred = truth - truth[:, :1]
    np.testing.assert_allclose(preds.millimetres[0] - preds.millimetres[0][:, :1], hip_centred, atol=1e-9)
    scores = table1.evaluate_c3dpo(preds, [seq])
    assert scores["Avg"][0] == pytest.approx(0.0, abs=1e-9) and scores["Walking"][1] == seq.n_frames


def test_c3dpo_protocol_averages_actions_unweighted_and_takes_the_better_flip():
    a, b = _h36m_like(4, action="Eating"), _h36m_like(12, action="Posing")
    pa = a.points_3d + np.array([10.0, 0.0, 0.0])  # every joint 10 mm off, but the hip centring removes a shift:
    pa[:, 1:] += np.array([0.0, 0.0, 10.0])  # the non-hip joints 10 mm deeper than the hip's offset
    pb = b.points_3d * np.array([1.0, 1.0, -1.0])  # a depth flip: the better of raw and flipped is exact
    preds = [_in_prn_units(p, t) for p, t in ((pa, a), (pb, b))]
    scores = table1.evaluate_c3dpo(preds, [a, b])
    eating = 10.0 * 16 / 17  # 16 of 17 joints off by 10 mm after hip centring
    assert scores["Eating"][0] == pytest.approx(eating) and scores["Posing"][0] == pytest.approx(0.0, abs=1e-9)
    assert scores["Avg"][0] == pytest.approx(eating / 2)  # unweighted over actions (frame-weighted: eating / 4)
    assert scores["Avg"][1] == 16
    prn = table1.evaluate(preds, [a, b])
    assert prn["Avg"][0] != pytest.approx(scores["Avg"][0])


def test_choose_data_reads_nrsfm_data_and_says_when_it_stands_in(tmp_path, monkeypatch):
    def args(**kw):
        return argparse.Namespace(**{"data": None, "root": None, **kw})

    monkeypatch.delenv("NRSFM_DATA", raising=False)
    a = args()
    assert "stand-in" in choose_data(a, [("h36m", ("h36m",))], "table1") and a.data == "synthetic"
    monkeypatch.setenv("NRSFM_DATA", str(tmp_path))
    a = args()
    notice = choose_data(a, [("h36m", ("h36m",))], "table1")
    assert a.data == "synthetic" and f"{tmp_path} holds no h36m" in notice
    (tmp_path / "h36m").mkdir()
    a = args()
    assert choose_data(a, [("h36m", ("h36m",))], "table1") is None and a.data == "h36m"
    assert a.root == str(tmp_path)
    a = args()  # the first candidate present wins
    (tmp_path / "aflw2000").mkdir()
    assert choose_data(a, [("300vw", ("300vw-3d",)), ("aflw2000", ("aflw2000",))], "table3") is None
    assert a.data == "aflw2000"
    with pytest.raises(ValidationError, match="--root: expected surreal under"):
        choose_data(args(root=str(tmp_path)), [("surreal", ("surreal",))], "table4")
    a = args(data="synthetic")
    assert choose_data(a, [("h36m", ("h36m",))], "table1") and a.data == "synthetic"


def test_prn_fcn_w_runs_on_scored_detections_and_says_why_not_otherwise(tmp_path):
    seqs = human_sequences(("S1", "S5"), ("walking",), (1,), n_frames=40)
    rng = np.random.default_rng(0)
    scored = [s.replace(visibility=rng.uniform(0.3, 1.0, s.points_2d.shape[:2])) for s in seqs]
    ctx = RunContext(out_dir=tmp_path, iterations=6, progress=False, width=16, group_size=8, groups=2)
    split = Split(scored, seqs, scored[:1], seqs[:1], "sh")
    preds = methods.prn_fcn_w(split, ctx)
    assert preds[0].shape == (40, 17, 3) and np.isfinite(preds[0]).all()
    key = json.loads((next((tmp_path / "cache").iterdir()) / "train.json").read_text())["config"]
    assert key["lam"] == 0.05
    binary = [s.replace(visibility=(s.weights > 0.5).astype(float)) for s in scored]
    with pytest.raises(NotRun, match="these detections carry no scores"):
        methods.prn_fcn_w(Split(binary, seqs, binary[:1], seqs[:1], "sh"), ctx)
