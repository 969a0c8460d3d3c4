import dataclasses

import numpy as np
import pytest
import torch

from nrsfm.datasets.synthetic import human_sequences
from nrsfm.errors import ValidationError
from prn.data import build_training_set, denormalize, normalize_2d, normalize_3d, unit_frames
from prn.model import PRNCNN, PRNFCN
from prn.train import TrainConfig, TrainingError, load_model, predict, train


@pytest.fixture(scope="module")
def small_set():
    seqs = human_sequences(("S1", "S5"), ("walking", "bending"), n_frames=60, takes=2)
    return build_training_set(seqs)


def test_normalisation_roundtrip():
    seq = human_sequences(("S9",), ("walking",), (2,), n_frames=10)[0]
    x, s = normalize_2d(seq.points_2d)
    np.testing.assert_allclose(np.linalg.norm(x.reshape(10, -1), axis=1), 1.0)
    np.testing.assert_allclose(x.mean(axis=1), 0.0, atol=1e-12)
    y, s3 = normalize_3d(seq.points_3d)
    np.testing.assert_allclose(s, s3)  # orthographic GT: the same xy norm
    np.testing.assert_allclose(denormalize(y, seq.points_3d), seq.points_3d - seq.points_3d.mean(1, keepdims=True))


def test_unit_frames_centres_and_scales_every_frame_to_a_unit_xy_norm():
    seq = human_sequences(("S1",), ("walking",), projection="perspective", n_frames=12, takes=1)[0]
    seq = seq.to_weak_perspective()
    unit = unit_frames(seq)
    np.testing.assert_allclose(unit.points_2d.mean(axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(unit.points_2d.reshape(seq.n_frames, -1), axis=1), 1.0, rtol=1e-9)
    centred = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    ratio = np.linalg.norm(centred.reshape(seq.n_frames, -1), axis=1)
    np.testing.assert_allclose(unit.points_2d * ratio[:, None, None], centred, rtol=1e-9, atol=1e-12)
    assert unit.name == seq.name and unit.meta == seq.meta  # the cuts see the same recordings and cameras


def test_test_inputs_normalised_on_visible_points_or_on_all_as_a_training_sample_drops_them(small_set):
    from nrsfm.datasets.synthetic import drop_entries

    seq = human_sequences(("S9",), ("walking",), (1,), n_frames=10)[0]
    dropped = drop_entries(seq, 0.3)
    seen = dropped.weights > 0
    x_vis, w = small_set.prepare_inputs(dropped)
    x_all, w_all = small_set.prepare_inputs(dropped, "all")
    np.testing.assert_array_equal(w, w_all)
    # "all": the complete frame's normalisation with the missing points zeroed, as train() drops points
    np.testing.assert_allclose(x_all, normalize_2d(seq.points_2d)[0] * seen[..., None])
    # "visible": centred on the visible points alone, their norm that of as many of P points at unit norm
    np.testing.assert_allclose((x_vis * seen[..., None]).sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(x_vis.reshape(10, -1), axis=1), np.sqrt(seen.mean(axis=1)))
    assert not np.allclose(x_vis, x_all)
    np.testing.assert_allclose(small_set.prepare_inputs(seq, "all")[0], small_set.prepare_inputs(seq)[0])
    with pytest.raises(ValidationError, match="normalise_on: expected 'visible' or 'all'"):
        small_set.prepare_inputs(seq, "none")


def test_multiview_groups_cycle_cameras_half_a_second_apart(small_set):
    assert len(small_set.streams) == 4  # 2 subjects x 2 takes
    assert all(s.shape[0] == 4 for s in small_set.streams)  # 4 cameras
    idx = small_set.sample_groups(np.random.default_rng(0), 1, 8, gap=5)
    stream = next(s for s in small_set.streams if idx[0] in s)
    pos = [np.argwhere(stream == i)[0] for i in idx]  # (camera, time)
    cams = [c for c, _ in pos]
    times = [t for _, t in pos]
    assert np.all(np.diff(times) == 5)
    assert all((b - a) % 4 == 1 for a, b in zip(cams, cams[1:]))


def test_sh_inputs_drop_the_undetected_joint():
    seqs = human_sequences(("S1",), ("walking",), n_frames=40, takes=2)
    vis = np.ones((40, 17))
    vis[:, 9] = 0
    det = [s.replace(visibility=vis) for s in seqs]
    ts = build_training_set(det, seqs)
    assert ts.n_inputs == 16 and ts.n_points == 17
    x, w = ts.prepare_inputs(det[0])
    assert x.shape == (40, 16, 2)


def test_fcn_shapes_and_initial_output_is_small():
    net = PRNFCN(17, 16, width=64)
    out = net(torch.randn(8, 16, 2))
    assert out.shape == (8, 17, 3) and out.abs().max() < 0.5
    with pytest.raises(ValidationError, match=r"expected \(N, 16, 2\)"):
        net(torch.randn(8, 17, 2))


def test_cnn_head_with_a_small_backbone():
    backbone = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, stride=4), torch.nn.ReLU())
    net = PRNCNN(17, backbone=backbone, feature_dim=4 * 8 * 8, width=32)
    assert net(torch.randn(2, 3, 34, 34)).shape == (2, 17, 3)


def test_cnn_with_the_torchvision_resnet50_trains_with_the_pr_loss():
    """Forward, PR loss and backward through the full ResNet-50 (skipped where torchvision does not import beside
    the installed torch)."""
    try:
        import torchvision  # noqa: F401
        torchvision.models.resnet50()
    except Exception as exc:  # ImportError or an operator mismatch ('torchvision::nms does not exist')
        pytest.skip(f"torchvision unusable here: {exc}")
    from prn.loss import pr_loss

    torch.manual_seed(0)
    net = PRNCNN(17).train()
    pred = net(torch.randn(4, 3, 224, 224))
    assert pred.shape == (4, 17, 3)
    pr_loss(pred, 0.2 * torch.randn(4, 17, 2), lam=0.05, group_size=4).backward()
    grads = [p.grad for p in net.backbone.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_prn_cnn_trains_on_rendered_images_saves_and_predicts(tmp_path):
    """PRN-CNN end to end on the stand-in's rendered images: the loss falls, the model reloads with the same
    predictions, and a configuration without images is refused."""
    pytest.importorskip("torchvision")
    from nrsfm.datasets.render import render_sequence
    from prn.images import ImageStack
    from prn.train import predict_images

    seqs = human_sequences(("S1",), ("walking", "bending"), n_frames=60, takes=1)
    images = [render_sequence(s, size=32) for s in seqs]
    data = build_training_set(seqs, images=images, sampling="random")
    assert data.images.shape == (len(data.inputs), 32, 32, 3)
    config = TrainConfig(iterations=40, lr=1e-3, lr_step=1000, checkpoint_every=20, group_size=16, width=64,
                         network="small", device="cpu")
    res = train(data, config, tmp_path, progress=False, log_every=5)
    first, last = res.history[0]["loss"], np.mean([h["loss"] for h in res.history[-3:]])
    assert last < 0.7 * first
    model = load_model(tmp_path / "model.pt", "cpu")
    assert isinstance(model, PRNCNN)
    np.testing.assert_allclose(predict_images(model, images[0]), predict_images(res.model, images[0]), atol=1e-5)
    lazy = ImageStack(images)  # any indexable image source trains alike
    np.testing.assert_array_equal(lazy[np.array([0, len(images[0]), 5])],
                                  np.concatenate(images)[[0, len(images[0]), 5]])
    with pytest.raises(ValidationError, match="carries no images"):
        train(build_training_set(seqs, sampling="random"), config, None, progress=False)
    with pytest.raises(ValidationError, match="network: expected 'fcn' or one of"):
        TrainConfig(network="vgg")
    with pytest.raises(ValidationError, match="one image source per input sequence"):
        build_training_set(seqs, images=images[:1])


@pytest.mark.parametrize("missing", [0.0, 0.2])  # 0.2: random point drops draw from torch's (device) RNG
def test_training_reduces_the_loss_and_checkpoints_resume(small_set, tmp_path, missing):
    cfg = TrainConfig(iterations=40, width=64, lr=1e-3, lr_step=20, checkpoint_every=20, group_size=8, groups=2,
                      missing_points=missing)
    full = train(small_set, cfg, tmp_path / "a", progress=False, log_every=1)
    assert full.history[-1]["loss"] < full.history[0]["loss"]
    # an interrupted run (stopped after 20 iterations) resumed to 40 gives the same weights
    part = train(small_set, cfg, tmp_path / "b", progress=False, stop_after=20)
    assert part.iterations_run == 20 and not (tmp_path / "b" / "model.pt").exists()
    resumed = train(small_set, cfg, tmp_path / "b", progress=False)
    assert resumed.iterations_run == 20 and (tmp_path / "b" / "model.pt").exists()
    for k, v in full.model.state_dict().items():
        torch.testing.assert_close(v, resumed.model.state_dict()[k], msg=k)
    with pytest.raises(ValidationError, match="another configuration"):
        train(small_set, TrainConfig(**{**cfg.__dict__, "lam": 0.5}), tmp_path / "b", progress=False)
    model = load_model(tmp_path / "a" / "model.pt")
    x, w = small_set.prepare_inputs(human_sequences(("S9",), ("walking",), (1,), n_frames=5)[0])
    np.testing.assert_allclose(predict(model, x, w), predict(full.model, x, w), atol=1e-6)


def test_ema_averages_the_weights_after_the_bn_freeze_keeps_its_statistics_and_resumes(small_set, tmp_path):
    cfg = TrainConfig(iterations=4, width=32, lr=1e-2, checkpoint_every=1, group_size=8, groups=2, ema=0.75,
                      bn_freeze_fraction=0.5)  # BN freezes at iteration 2: steps 3 and 4 are averaged
    seen = []
    for _ in range(4):  # one iteration a call; each checkpoint holds that iteration's live weights
        res = train(small_set, cfg, tmp_path / "e", progress=False, stop_after=1)
        seen.append(torch.load(tmp_path / "e" / "checkpoint.pt", weights_only=False)["model"])
    w3, w4 = seen[2], seen[3]
    buffers = {name for name, _ in res.model.named_buffers()}
    assert any(name.endswith("running_var") for name in buffers)
    for k, v in res.model.state_dict().items():
        if k in buffers:  # the statistics frozen at iteration 2, which steps 3 and 4 trained with
            torch.testing.assert_close(v, w4[k], msg=k)
            torch.testing.assert_close(v, w3[k], msg=k)
        else:  # the first averaged step copies
            torch.testing.assert_close(v, (0.75 * w3[k] + 0.25 * w4[k]).to(v.dtype), msg=k)
    last = train(small_set, dataclasses.replace(cfg, ema=0.0), tmp_path / "l", progress=False)
    for k, v in last.model.state_dict().items():  # the same trajectory; without averaging, its last iterate
        torch.testing.assert_close(v, w4[k], msg=k)
    assert not torch.allclose(next(res.model.parameters()), next(last.model.parameters()))
    with pytest.raises(ValidationError, match="ema"):
        TrainConfig(ema=1.0)
    with pytest.raises(ValidationError, match="bn_freeze_fraction"):
        TrainConfig(ema=0.9, bn_freeze_fraction=0.0)


def test_nan_loss_stops_with_a_clear_error(small_set, tmp_path):
    bad = build_training_set(human_sequences(("S1",), ("walking",), n_frames=60, takes=1))
    bad.targets[:] = np.nan
    with pytest.raises(TrainingError, match="the loss became nan at iteration 0"):
        train(bad, TrainConfig(iterations=5, width=16, group_size=8, groups=1), tmp_path, progress=False)


def test_renormalise_is_normalize_2d_of_the_kept_points_and_scales_a_3d_target_alike():
    from prn.train import renormalise

    seq = human_sequences(("S9",), ("walking",), (1,), n_frames=6)[0]
    keep = np.random.default_rng(0).random((6, 17)) > 0.3
    x = torch.as_tensor(normalize_2d(seq.points_2d)[0])
    np.testing.assert_allclose(renormalise(x, torch.as_tensor(keep)).numpy(),
                               normalize_2d(seq.points_2d, keep)[0], atol=1e-12)
    # a frame's size does not depend on how many points it keeps: as many points at unit norm as it has
    assert np.isclose(np.linalg.norm(normalize_2d(seq.points_2d, keep)[0][0]), np.sqrt(keep[0].mean()))
    # a 3D target keeps every point, moved and scaled as its 2D; denormalize with the same points undoes it
    y3 = renormalise(torch.tensor(seq.points_3d), torch.as_tensor(keep), zero_missing=False).numpy()
    np.testing.assert_allclose(y3[..., :2][keep], normalize_2d(seq.points_2d, keep)[0][keep], atol=1e-12)
    back = denormalize(y3, seq.points_3d, keep)
    np.testing.assert_allclose(back - back.mean(1, keepdims=True),
                               seq.points_3d - seq.points_3d.mean(1, keepdims=True), atol=1e-9)


def test_missing_points_normalised_on_the_visible_ones_in_training(small_set, monkeypatch):
    """``missing_normalise="visible"``: each training sample's input and 2D targets are normalised on the points
    it keeps (no hidden point's 2D enters), and a supervised 3D target alike."""
    seen = []
    forward = PRNFCN.forward

    def spy_forward(self, x, w=None):
        seen.append((x.detach().clone(), w.detach().clone()))
        return forward(self, x, w)

    monkeypatch.setattr(PRNFCN, "forward", spy_forward)
    cfg = TrainConfig(iterations=3, width=32, group_size=8, groups=2, missing_points=0.3, missing_normalise="visible")
    assert np.isfinite(train(small_set, cfg, progress=False).history[-1]["loss"])
    x, w = seen[0]
    kept = (w > 0).unsqueeze(-1)
    torch.testing.assert_close((x * kept).sum(1), torch.zeros(len(x), 2), atol=1e-5, rtol=0)
    torch.testing.assert_close(x.flatten(1).norm(dim=1), kept[..., 0].float().mean(1).sqrt(), atol=1e-5, rtol=0)
    assert (x[~kept[..., 0]] == 0).all()
    # the same run with "all" feeds inputs normalised with the hidden points (not centred on the kept ones)
    seen.clear()
    train(small_set, dataclasses.replace(cfg, missing_normalise="all"), progress=False)
    x, w = seen[0]
    assert (x * (w > 0).unsqueeze(-1)).sum(1).abs().max() > 1e-2
    from baselines.supervised import train_supervised

    seqs = human_sequences(("S1",), ("walking",), n_frames=40, takes=1)
    res, _ = train_supervised(seqs, [s.points_3d for s in seqs], dataclasses.replace(cfg, width=16), None,
                              progress=False)
    assert np.isfinite(res.history[-1]["loss"])
    with pytest.raises(ValidationError, match="missing_normalise: expected 'all' or 'visible'"):
        TrainConfig(missing_normalise="some")


def test_scores_weigh_the_data_term():
    """PRN-FCN-W: the data term weighs each target point by the input's detection score (its visibility)."""
    seqs = human_sequences(("S1",), ("walking",), (1,), n_frames=12)
    rng = np.random.default_rng(0)
    scored = [s.replace(visibility=rng.uniform(0.2, 1.0, s.points_2d.shape[:2])) for s in seqs]
    data = build_training_set(scored, seqs, sampling="random", scores=True)
    np.testing.assert_allclose(data.target_weights, np.concatenate([s.visibility for s in scored]))
    np.testing.assert_allclose(build_training_set(scored, seqs, sampling="random").target_weights, 1.0)


def test_schedule():
    cfg = TrainConfig()
    assert cfg.phase_boundary == 49_000
    assert cfg.lr_at(0) == 1e-4 and cfg.lr_at(5000) == pytest.approx(0.8e-4)
    assert cfg.lr_at(49_000) == 1e-4  # the frozen-BN phase restarts the schedule, as the official code
    with pytest.raises(ValidationError):
        TrainConfig(group_size=1)


def test_random_and_consecutive_sampling():
    seqs = human_sequences(("S1",), ("walking", "waving"), (1,), n_frames=30)
    rnd = build_training_set(seqs, sampling="random")
    idx = rnd.sample_groups(np.random.default_rng(0), 3, 10)
    assert len(idx) == 30 and len(set(idx[:10])) == 10
    con = build_training_set(seqs, sampling="consecutive")
    idx = con.sample_groups(np.random.default_rng(0), 2, 10)
    assert np.all(np.diff(idx[:10]) == 1) and np.all(np.diff(idx[10:]) == 1)
    with pytest.raises(ValidationError, match="no sequence has"):
        con.sample_groups(np.random.default_rng(0), 1, 31)


@pytest.mark.parametrize("in_loss", [True, False])
def test_missing_points_leave_the_input_and_optionally_the_data_term(small_set, monkeypatch, in_loss):
    import prn.train

    seen = {"x": [], "y": []}
    forward, loss = PRNFCN.forward, prn.train.pr_loss

    def spy_forward(self, x, w=None):
        seen["x"].append(w.detach().clone())
        return forward(self, x, w)

    def spy_loss(pred, y, yw, **kw):
        seen["y"].append(yw.detach().clone())
        return loss(pred, y, yw, **kw)

    monkeypatch.setattr(PRNFCN, "forward", spy_forward)
    monkeypatch.setattr(prn.train, "pr_loss", spy_loss)
    res = train(small_set, TrainConfig(iterations=5, width=32, group_size=8, groups=2, missing_points=0.3,
                                       missing_in_loss=in_loss), progress=False)
    assert np.isfinite(res.history[-1]["loss"])
    xw, yw = torch.cat(seen["x"]), torch.cat(seen["y"])
    assert 0.2 < (xw == 0).float().mean().item() < 0.4  # the input loses about 30% of its points
    if in_loss:
        torch.testing.assert_close(yw, xw)  # the same points weigh 0 in the data term
    else:
        assert (yw == 1).all()  # the data term keeps every point's 2D
    if in_loss:  # a supervised 3D objective: the points leave the input, the targets keep every point
        from baselines.supervised import train_supervised

        seqs = human_sequences(("S1",), ("walking",), n_frames=40, takes=1)
        seen["x"].clear()
        train_supervised(seqs, [s.points_3d for s in seqs], TrainConfig(iterations=5, width=16, group_size=8,
                                                                        groups=2, missing_points=0.3), None,
                         progress=False)
        assert 0.2 < (torch.cat(seen["x"]) == 0).float().mean().item() < 0.4


def test_training_leaves_denormals_enabled(small_set):
    import sys

    train(small_set, TrainConfig(iterations=2, width=16, group_size=8, groups=1), progress=False)
    assert (torch.tensor([sys.float_info.min], dtype=torch.float64) / 4).item() > 0  # subnormals representable
    assert np.float64(sys.float_info.min) / 4 > 0


def test_point_groups_split_every_frame_alike_and_train():
    from prn.train import _point_groups

    pred = torch.arange(2 * 7 * 3, dtype=torch.float32).reshape(2, 7, 3)
    y, w = pred[..., :2].clone(), torch.ones(2, 7)
    gp, gy, gw = _point_groups(pred, y, w, 3)
    assert gp.shape == (6, 2, 3) and gy.shape == (6, 2, 2) and gw.shape == (6, 2)
    # rows k*N .. k*N + N - 1 hold point group k of every frame: the same points in each frame
    idx = gp[..., 0] / 3 % 7  # point index of each entry
    for k in range(3):
        assert torch.equal(idx[2 * k], idx[2 * k + 1])
    assert len(set(idx.flatten().tolist())) == 6  # six distinct points (one left out)
    torch.testing.assert_close(gy, gp[..., :2])
    seqs = human_sequences(("S1",), ("walking",), (1,), n_frames=40)
    data = build_training_set(seqs, sampling="consecutive")
    res = train(data, TrainConfig(iterations=5, width=32, group_size=8, groups=2, point_groups=2), progress=False)
    assert np.isfinite(res.history[-1]["loss"])
    with pytest.raises(ValidationError, match="point_groups"):
        TrainConfig(point_groups=0)
