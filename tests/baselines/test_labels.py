"""The pseudo-label pipeline: cuts, solves, the cache and its resume, the Dask backend, reflections."""

import numpy as np
import pytest

import baselines.labels as labels
from baselines.labels import make_labels, multiview_cuts, resolve_reflections, solve_cuts
from nrsfm.datasets.synthetic import human_sequences


@pytest.fixture(scope="module")
def walk():
    """One subject's two motions seen by the 4 ring cameras, 30 frames at 10 fps (orthographic)."""
    return human_sequences(("S1",), ("walking", "bending"), projection="orthographic", n_frames=30, takes=1)


def test_cuts_hold_every_frame_and_camera_once_with_the_camera_cycling(walk):
    cuts = multiview_cuts(walk, gap=5)
    assert len(cuts) == 2 * 5 * 4  # recordings x offsets x camera phases
    seen = np.zeros((len(walk), 30), int)
    for cut in cuts:
        i, t = cut.sources.T
        seen[i, t] += 1
        assert np.all(np.diff(t) == 5)
        cams = [walk[j].meta["camera"] for j in i]
        assert all(int(b) == int(a) % 4 + 1 for a, b in zip(cams, cams[1:]))  # 1, 2, 3, 4, 1, ...
        np.testing.assert_array_equal(cut.sequence.points_2d, np.stack([walk[j].points_2d[f] for j, f in zip(i, t)]))
        assert cut.sequence.points_3d is None  # the solver sees 2D only
    assert (seen == 1).all()


def test_reflections_are_resolved_to_one_handedness_without_ground_truth():
    """True camera-frame shapes of six motions (upright, bending, sitting, ...), 40% of the cuts mirrored: every
    cut ends with one handedness, though the poses change the sign of most 4-point volumes."""
    seqs = human_sequences(("S1", "S5"), projection="orthographic", n_frames=30, takes=1)
    cuts = multiview_cuts(seqs)[::2]
    shapes = [np.stack([seqs[i].points_3d[t] for i, t in c.sources]) for c in cuts]
    mirrored = np.random.default_rng(1).random(len(shapes)) < 0.4
    flips = resolve_reflections([s * np.array([1, 1, -1]) if m else s for s, m in zip(shapes, mirrored)])
    np.testing.assert_array_equal(flips, mirrored)
    assert not resolve_reflections([np.full((4, 17, 3), np.nan)]).any()


def test_label_pipeline_resumes_and_records_failures(walk, tmp_path, monkeypatch):
    cuts = multiview_cuts(walk[:4], gap=5)  # one recording: 20 cuts of 6 frames
    calls = []
    real = labels._solve_cut

    def counted(*args):
        calls.append(args[2])
        if len(calls) == 7 and not hasattr(counted, "interrupted"):
            counted.interrupted = True
            raise KeyboardInterrupt  # an interruption after 6 finished cuts
        return real(*args)

    monkeypatch.setattr(labels, "_solve_cut", counted)
    rank = labels.LABEL_DEFAULTS["csf2"]  # the pipeline's one-solve K rule (the default solves every K)
    with pytest.raises(KeyboardInterrupt):
        solve_cuts(cuts, "csf2", rank, out_dir=tmp_path, dataset="walk", progress=False)
    calls.clear()
    shapes, failed, reused = solve_cuts(cuts, "csf2", rank, out_dir=tmp_path, dataset="walk", progress=False)
    assert reused == 6 and len(calls) == 14  # only the unfinished cuts are solved
    assert not failed and all(np.isfinite(s).all() for s in shapes)
    calls.clear()
    assert solve_cuts(cuts, "csf2", rank, out_dir=tmp_path, dataset="walk", progress=False)[2] == 20 and not calls
    # a solver that refuses the input: recorded, never replaced
    bad, failed, _ = solve_cuts(cuts[:2], "csf2", {"K": 7}, out_dir=tmp_path, dataset="walk", progress=False)
    assert len(failed) == 2 and "K = 7" in next(iter(failed.values())) and np.isnan(bad[0]).all()


def test_labels_end_to_end_and_the_dask_backend_gives_the_same(walk, tmp_path):
    result = make_labels(walk, "csf2", out_dir=tmp_path / "local", dataset="walk", progress=False)
    s = result.summary
    assert s["cuts"] == 40 and s["failed"] == 0 and s["labelled_frames"] == s["frames"] == 240
    assert s["label_mpjpe"] < 150  # mm, PRN protocol; the subject is about 1.7 m tall
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        other = make_labels(walk, "csf2", out_dir=tmp_path / "dask", dataset="walk", backend="dask",
                            scheduler=cluster.scheduler_address, progress=False)
    for a, b in zip(result.labels, other.labels):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_a_point_no_frame_shows_is_left_unlabelled_and_the_rest_labelled(walk, tmp_path):
    """The Stacked Hourglass detections have no Neck/Nose (point 9): each cut is solved on the points it shows, the
    hidden point's label is NaN, every frame keeps its label, the reflections are still resolved on the others."""
    hidden = [s.replace(visibility=np.ones((s.n_frames, s.n_points)) * (np.arange(s.n_points) != 9))
              for s in walk]
    full = make_labels(walk, "csf2", out_dir=tmp_path, dataset="full", progress=False)
    part = make_labels(hidden, "csf2", out_dir=tmp_path, dataset="hidden", progress=False)
    s = part.summary
    assert s["failed"] == 0 and s["labelled_frames"] == s["frames"] == 240 and s["unlabelled_points"] == 240
    for lab in part.labels:
        assert np.isnan(lab[:, 9]).all() and np.isfinite(np.delete(lab, 9, axis=1)).all()
    # mirrored to one handedness on the 16 points: most frames' depth agrees in sign with the truth's, or most
    # disagree (the one global ambiguity); CSF2 on 6-frame cuts: 70% of the frames (all 17 points: 76%)
    assert s["mirrored"] > 0
    keep = np.arange(17) != 9
    z = lambda a: a[:, keep, 2] - a[:, keep, 2].mean(axis=1, keepdims=True)  # noqa: E731
    agree = np.concatenate([(z(lab) * z(w.points_3d)).sum(axis=1) > 0 for lab, w in zip(part.labels, walk)])
    assert max(agree.mean(), 1 - agree.mean()) > 0.65
    # scored on the 16 labelled points, about as good as the labels of all 17 (136 and 95 mm here)
    assert s["label_mpjpe"] < 2 * full.summary["label_mpjpe"]
    # the targets a network learns: finite on the labelled points, normalised as an input on its visible points
    from baselines.supervised import Supervised3D, normalised_targets
    from prn.data import normalize_2d

    targets = normalised_targets(part.labels)
    assert np.isnan(targets[:, 9]).all() and np.isfinite(np.delete(targets, 9, axis=1)).all()
    weights = np.concatenate([h.weights for h in hidden])
    x2d, _ = normalize_2d(np.nan_to_num(np.concatenate(part.labels))[..., :2], weights)
    np.testing.assert_allclose(np.nan_to_num(targets[..., :2]), x2d, atol=1e-9)
    objective = Supervised3D(targets, batch=8)
    assert len(objective.labelled) == 240 and not objective.every_point
    import torch

    idx = torch.arange(8)
    exact = torch.as_tensor(np.nan_to_num(targets[:8]), dtype=torch.float32)
    wrong_hidden = exact.clone()
    wrong_hidden[:, 9] += 5.0  # the unlabelled point costs nothing
    assert objective.loss(exact, idx) == 0 and objective.loss(wrong_hidden, idx) == 0


def test_labels_of_perspective_tracks_are_scored_against_the_millimetre_ground_truth(tmp_path):
    persp = human_sequences(("S1",), ("walking",), projection="perspective", n_frames=30, takes=1)
    weak = [s.to_weak_perspective() for s in persp]  # their ground truth divided by each frame's depth
    scored = make_labels(weak, "csf2", out_dir=tmp_path, dataset="p", progress=False, truth=persp)
    assert scored.summary["label_mpjpe"] > 20  # mm, PRN protocol (CSF2 on 30 close-up frames: poor labels)
    own_units = make_labels(weak, "csf2", out_dir=tmp_path, dataset="p", progress=False)
    # in the converted tracks' units (millimetres / depth, about 3.5 m here) the same labels err 1 / 3,500 as much
    assert own_units.summary["label_mpjpe"] < 0.01 * scored.summary["label_mpjpe"]


def test_labels_refuse_perspective_tracks_and_unknown_settings(walk, tmp_path):
    persp = human_sequences(("S1",), ("walking",), projection="perspective", n_frames=10, takes=1)
    with pytest.raises(ValueError, match="orthographic"):
        make_labels(persp, "csf2", out_dir=tmp_path, dataset="p", progress=False)
    with pytest.raises(ValueError, match="no parameter 'k'"):
        solve_cuts(multiview_cuts(walk[:4]), "csf2", {"k": 3}, out_dir=tmp_path, dataset="w", progress=False)
    with pytest.raises(ValueError, match="backend"):
        solve_cuts(multiview_cuts(walk[:4]), "csf2", out_dir=tmp_path, dataset="w", backend="ray", progress=False)


def test_a_root_without_human36m_is_an_error_not_the_stand_in(tmp_path, capsys):
    code = labels.main(["--root", str(tmp_path), "--out", str(tmp_path / "labels"), "--no-progress"])
    assert code == 2 and "h36m: expected a dataset folder" in capsys.readouterr().err
    assert not (tmp_path / "labels").exists()  # nothing was solved


def test_labels_cli_fails_when_every_cut_fails(tmp_path, capsys, monkeypatch):
    tiny = human_sequences(("S1",), ("walking",), projection="orthographic", n_frames=10, takes=1)  # 2-frame cuts
    monkeypatch.setattr(labels, "_training_sequences", lambda args: (tiny, "tiny"))
    code = labels.main(["--method", "csf2", "--out", str(tmp_path), "--no-progress", "--jobs", "1"])
    err = capsys.readouterr().err
    assert code == 1 and "every one of the 20 cuts failed" in err and "SolverError" in err
