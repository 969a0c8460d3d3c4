"""C3DPO: the canonicalisation loss, the pseudo-Huber reprojection, training and prediction."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from baselines.c3dpo import (C3DPO, C3DPOConfig, TrainStep, make_optimizer, predict_c3dpo, pseudo_huber,
                             random_rotations, train_c3dpo, warm_up)
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.procrustes import rotation_exp

SMALL = C3DPOConfig(basis=3, width=64, n_layers=1, iterations=30, batch=32, checkpoint_every=10)


def test_canonicalisation_loss_is_zero_for_a_canonical_shape_and_positive_for_a_rotated_copy(monkeypatch):
    torch.manual_seed(0)
    model = C3DPO(12, SMALL)
    canonical = torch.randn(1, 3, 12, dtype=torch.float32)
    canonical = canonical - canonical.mean(dim=2, keepdim=True)
    # a perfect canonicaliser of this shape's orbit: whatever rotation it sees, it returns the canonical shape
    monkeypatch.setattr(model, "canonicalise", lambda shapes: canonical.expand(len(shapes), -1, -1))
    floor = pseudo_huber(torch.zeros(()), SMALL.huber)  # the loss of an exact match (its 1e-4 smoothing)
    assert float(model.canonicalisation_loss(canonical)) == pytest.approx(float(floor), abs=1e-9)
    assert float(floor) < 1e-6
    turned = rotation_exp(torch.tensor([[0.0, 0.0, math.pi / 2]])) @ canonical
    assert float(model.canonicalisation_loss(turned)) > 100 * float(floor)


def test_pseudo_huber_is_quadratic_near_zero_and_linear_far_away():
    c = 0.01
    small, large = torch.tensor(1e-8), torch.tensor(1.0)
    floor = float(pseudo_huber(torch.zeros(()), c))
    assert float(pseudo_huber(small, c)) == pytest.approx(float(small) / (2 * c) + floor, rel=1e-3)
    assert float(pseudo_huber(large, c)) == pytest.approx(1.0 - c, rel=1e-3)


def test_random_rotations_are_proper_and_respect_the_axis_mask():
    r = random_rotations(50, math.pi / 8, (0.0, 0.0, 1.0), like=torch.zeros(1, dtype=torch.float64))
    np.testing.assert_allclose(torch.linalg.det(r).numpy(), 1.0, atol=1e-12)
    np.testing.assert_allclose(r[:, 2, 2].numpy(), 1.0, atol=1e-12)  # about the optical axis only
    assert float(torch.arccos(r[:, 0, 0].clamp(-1, 1)).max()) <= math.pi / 8 + 1e-9


def test_c3dpo_trains_resumes_and_keeps_the_input_coordinates(tmp_path):
    seq = lowrank_sequence(200, 12, 2, seed=0)
    x = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    x = x / np.linalg.norm(x.reshape(len(x), -1), axis=1)[:, None, None]
    w = np.ones(x.shape[:2])
    w[::7, 3] = 0.0  # a few missing points
    model, record = train_c3dpo(x, w, SMALL, tmp_path, progress=False)
    assert record["iterations_run"] == 30 and (tmp_path / "model.pt").exists()
    hist = record["history"]
    assert all(np.isfinite(h["reprojection"]) and np.isfinite(h["canonicalisation"]) for h in hist)
    again, record2 = train_c3dpo(x, w, SMALL, tmp_path, progress=False)  # the checkpoint is at the end: no work
    assert record2["iterations_run"] == 0
    pred = predict_c3dpo(model, x[:20], w[:20])
    assert pred.shape == (20, 12, 3) and np.isfinite(pred).all()
    seen = w[:20] > 0
    np.testing.assert_allclose(pred[..., :2][seen], (x[:20] - (x[:20] * w[:20, :, None]).sum(1, keepdims=True)
                                                     / w[:20].sum(1)[:, None, None])[seen], atol=1e-6)
    with pytest.raises(ValueError, match="another configuration"):
        train_c3dpo(x, w, C3DPOConfig(basis=4, width=64, n_layers=1, iterations=30, batch=32), tmp_path,
                    progress=False)


def test_repeat_uses_each_minibatch_for_that_many_iterations_and_resumes_inside_a_group(tmp_path, monkeypatch):
    seq = lowrank_sequence(60, 12, 2, seed=1)
    x = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    w = np.ones(x.shape[:2])
    config = dataclasses.replace(SMALL, iterations=12, checkpoint_every=5, repeat=4)
    seen = []
    call = TrainStep.__call__

    def spy(self, idx, lr):
        seen.append(np.array(idx))
        return call(self, idx, lr)

    monkeypatch.setattr(TrainStep, "__call__", spy)
    whole, _ = train_c3dpo(x, w, config, tmp_path / "whole", progress=False)
    groups = [seen[i:i + 4] for i in range(0, 12, 4)]
    assert all(np.array_equal(g[0], r) for g in groups for r in g)  # four iterations on one minibatch
    assert not np.array_equal(groups[0][0], groups[1][0])
    # interrupted in iteration 8; the last checkpoint (after 5) falls inside the second group
    seen.clear()

    def interrupted(self, idx, lr):
        if len(seen) == 7:
            raise KeyboardInterrupt
        return spy(self, idx, lr)

    monkeypatch.setattr(TrainStep, "__call__", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_c3dpo(x, w, config, tmp_path / "cut", progress=False)
    seen.clear()
    monkeypatch.setattr(TrainStep, "__call__", spy)
    resumed, record = train_c3dpo(x, w, config, tmp_path / "cut", progress=False)
    assert record["iterations_run"] == 7
    assert np.array_equal(seen[0], groups[1][0]) and np.array_equal(seen[-1], groups[2][0])
    # the same weights up to rounding: on a GPU (config device "auto") the backward's atomic additions run in no fixed
    # order (1.6e-5 seen at one weight near 0 on an H200); a lost momentum moves them by 2e-4, a wrong minibatch or
    # other random rotations (the GPU's generator not restored) by 2e-3
    for a, b in zip(whole.state_dict().values(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=5e-5)
    assert "repeat" not in SMALL.key() and config.key()["repeat"] == 4  # old caches keep their key
    with pytest.raises(ValueError, match="repeat >= 1"):
        dataclasses.replace(SMALL, repeat=0)


def test_a_diverging_training_is_stopped_with_a_clear_error_and_writes_no_model(tmp_path):
    seq = lowrank_sequence(200, 12, 2, seed=0)
    x = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    # an lr far too large: the weights overflow within the first checkpoint interval, where the loss is checked
    config = dataclasses.replace(SMALL, lr=1e12, iterations=50, checkpoint_every=20)
    with pytest.raises(ValueError, match="lower the learning rate"):
        train_c3dpo(x, np.ones(x.shape[:2]), config, tmp_path, progress=False)
    assert not (tmp_path / "model.pt").exists() and not (tmp_path / "checkpoint.pt").exists()


def test_keypoint_rescale_scales_the_networks_inputs_and_divides_their_shapes_back():
    torch.manual_seed(0)
    small = dict(basis=3, width=16, n_layers=1)
    plain = C3DPO(6, C3DPOConfig(**small)).eval()
    scaled = C3DPO(6, C3DPOConfig(keypoint_rescale=2.5, **small)).eval()
    scaled.load_state_dict(plain.state_dict())
    rng = np.random.default_rng(0)
    x, v = rng.standard_normal((5, 6, 2)), np.ones((5, 6))
    v[0, 2] = 0.0  # one hidden point: its xy come from the network too
    ours = predict_c3dpo(scaled, x, v)
    theirs = predict_c3dpo(plain, 2.5 * x, v) / 2.5  # the same networks seeing the rescaled keypoints
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-6)
    with pytest.raises(Exception, match="keypoint_rescale"):
        C3DPOConfig(keypoint_rescale=0.0)


def test_the_adam_breed_is_adam_and_lowers_the_reprojection_loss(tmp_path):
    seq = lowrank_sequence(200, 12, 2, seed=0)
    x = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    x = x / np.linalg.norm(x.reshape(len(x), -1), axis=1)[:, None, None]
    config = C3DPOConfig(basis=3, width=64, n_layers=1, iterations=200, batch=32, checkpoint_every=100,
                         optimizer="adam")
    _, record = train_c3dpo(x, np.ones(x.shape[:2]), config, tmp_path, progress=False)
    hist = record["history"]
    assert hist[-1]["reprojection"] < 0.7 * hist[0]["reprojection"]
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)["optimizer"]["state"]
    assert all("exp_avg_sq" in s for s in state.values())  # Adam's second moments, which SGD has not
    with pytest.raises(Exception, match="optimizer"):
        C3DPOConfig(optimizer="rmsprop")


def test_the_monitor_runs_at_every_checkpoint_in_eval_mode(tmp_path):
    seq = lowrank_sequence(100, 12, 2, seed=0)
    x = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    w = np.ones(x.shape[:2])
    modes = []

    def monitor(model):
        modes.append(model.training)
        return {"n_points": model.n_points}

    config = C3DPOConfig(basis=3, width=32, n_layers=1, iterations=20, batch=16, checkpoint_every=10)
    _, record = train_c3dpo(x, w, config, tmp_path, progress=False, monitor=monitor)
    assert record["monitor"] == [{"iteration": 10, "n_points": 12}, {"iteration": 20, "n_points": 12}]
    assert modes == [False, False]


def test_bf16_runs_the_trunks_in_bfloat16_and_keeps_the_outputs_and_weights_float32():
    torch.manual_seed(0)
    w, v = torch.randn(16, 2, 12) * 0.3, torch.ones(16, 12)
    fp32 = C3DPO(12, dataclasses.replace(SMALL, width=64)).eval()
    bf16 = C3DPO(12, dataclasses.replace(SMALL, width=64, precision="bf16")).eval()
    bf16.load_state_dict(fp32.state_dict())
    dtypes = []
    bf16.phi[0].register_forward_hook(lambda mod, inp, out: dtypes.append(out.dtype))
    a, b = fp32(w, v)["camera"], bf16(w, v)["camera"]
    assert dtypes == [torch.bfloat16] and b.dtype == torch.float32
    assert not torch.equal(a, b) and torch.allclose(a, b, atol=0.05 * a.abs().max().item())
    assert all(p.dtype == torch.float32 for p in bf16.parameters())
    with pytest.raises(Exception, match="precision"):
        C3DPOConfig(precision="fp16")


def _step(config, n=64, seed=0):
    torch.manual_seed(seed)
    model = C3DPO(12, config).train()
    w, v = torch.randn(n, 2, 12) * 0.3, torch.ones(n, 12)
    v[::5, 2] = 0.0
    return TrainStep(model, make_optimizer(model, config), w, v, config.batch)


@pytest.mark.parametrize("trained_before", [0, 2])
def test_the_warm_up_before_a_cuda_graph_capture_leaves_the_training_where_it_was(trained_before):
    # a capture warms up on real iterations, then must put parameters, batch-norm statistics, momentum and the
    # random generator back: the next iteration (its random rotations too) is exactly the one without the warm-up
    config = dataclasses.replace(SMALL, batch=16)
    plain, warmed = _step(config), _step(config)
    rows = np.random.default_rng(0).integers(0, 64, (3, 16))
    for r in rows[:trained_before]:
        for s in (plain, warmed):
            torch.manual_seed(7)
            s(r, 0.01)
    warmed.idx.copy_(torch.from_numpy(rows[2]))
    torch.manual_seed(1)
    before = torch.get_rng_state()
    warm_up(warmed, 3)
    assert torch.equal(torch.get_rng_state(), before)
    warmed(rows[2], 0.01)
    torch.manual_seed(1)
    plain(rows[2], 0.01)
    for (name, a), b in zip(plain.model.state_dict().items(), warmed.model.state_dict().values()):
        assert torch.equal(a, b), name
    for p, q in zip(plain.model.parameters(), warmed.model.parameters()):
        assert torch.equal(plain.opt.state[p]["momentum_buffer"], warmed.opt.state[q]["momentum_buffer"])


def test_a_compiled_iteration_gives_what_op_by_op_launches_give():
    # torch.compile fuses kernels but must keep the arithmetic and the random rotations (fallback_random): two
    # iterations from the same seed give the same losses, parameters and batch-norm statistics to rounding
    config = dataclasses.replace(SMALL, batch=16)
    plain, compiled = _step(config), _step(config)
    compiled = TrainStep(compiled.model, compiled.opt, compiled.w_all, compiled.v_all, 16, compile=True)
    rows = np.random.default_rng(0).integers(0, 64, (2, 16))
    losses = []
    for s in (plain, compiled):
        torch.manual_seed(3)
        losses.append([torch.stack(s(r, 0.05)).tolist() for r in rows])
    np.testing.assert_allclose(losses[0], losses[1], rtol=1e-4)
    assert losses[0][0] != losses[0][1]  # the second iteration saw other rows and updated weights
    for (name, a), b in zip(plain.model.state_dict().items(), compiled.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6, msg=name)


def test_a_cuda_graph_is_refused_without_a_gpu_or_with_adam():
    config = dataclasses.replace(SMALL, batch=16)
    s = _step(config)
    with pytest.raises(ValueError, match="CUDA graph needs a CUDA device and SGD"):
        TrainStep(s.model, s.opt, s.w_all, s.v_all, 16, cuda_graph=True)
    with pytest.raises(ValueError, match="CUDA graph"):
        train_c3dpo(np.zeros((20, 12, 2)), np.ones((20, 12)), dataclasses.replace(config, device="cpu"), None,
                    progress=False, cuda_graph=True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_graph_training_follows_op_by_op_training_through_a_learning_rate_drop(tmp_path):
    seq = lowrank_sequence(400, 12, 2, seed=0)
    x = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    x = x / np.linalg.norm(x.reshape(len(x), -1), axis=1)[:, None, None]
    config = C3DPOConfig(basis=3, width=64, n_layers=1, iterations=300, batch=64, lr=1e-2, device="cuda",
                         checkpoint_every=150)
    records = [train_c3dpo(x, np.ones(x.shape[:2]), config, tmp_path / str(g), progress=False, cuda_graph=g)[1]
               for g in (False, True)]
    assert records[1]["cuda_graph"] and not records[0]["cuda_graph"]
    first, last = [[r["history"][i]["reprojection"] for r in records] for i in (0, -1)]
    assert last[1] < 0.8 * first[1]  # the replays train (op by op on a CPU: .259 to .184)
    assert abs(last[1] - last[0]) < 0.25 * last[0]  # as far as launching op by op does (another random stream)


def test_the_speed_study_times_both_precisions_and_refuses_a_bad_batch(tmp_path, capsys):
    import json

    from benchmarks.studies import speed_c3dpo

    assert speed_c3dpo.main(["--batch", "8", "--repeats", "1", "--warmup", "0", "--device", "cpu",
                             "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "speed_c3dpo.json").read_text())
    assert [r["precision"] for r in out["results"]] == ["fp32", "bf16"]
    assert all(r["iteration_s"] > 0 and r["speedup"] > 0 for r in out["results"])
    assert out["results"][0]["speedup"] == 1.0 and not any(r["compile"] for r in out["results"])
    assert "times faster" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        speed_c3dpo.main(["--batch", "1", "--out", str(tmp_path)])
    assert exc.value.code == 2


def test_c3dpo_recovers_the_depth_of_low_rank_shapes_seen_from_many_views():
    # shapes from a mean and a 2-shape basis, turned mostly about the vertical axis, seen orthographically:
    # exactly C3DPO's model, so its depth must beat a flat reconstruction by far on held-out frames (views as of a
    # standing body; lowrank_sequence turns its cameras uniformly, upside down too)
    rng = np.random.default_rng(0)
    n_points, n = 17, 6000
    mean = rng.normal(size=(3, n_points))
    mean -= mean.mean(axis=1, keepdims=True)
    mean /= np.linalg.norm(mean)
    shapes = mean + np.einsum("nk,kdp->ndp", rng.normal(size=(n, 2)), rng.normal(size=(2, 3, n_points)) * 0.15)
    turns = rotation_exp(torch.tensor(rng.normal(size=(n, 3)) * np.array([0.3, 2.0, 0.3]))).numpy()
    camera = turns @ shapes
    camera -= camera.mean(axis=2, keepdims=True)
    w, v = camera[:, :2].transpose(0, 2, 1), np.ones((n, n_points))
    config = C3DPOConfig(width=256, n_layers=1, iterations=2000, batch=128, lr=1e-2, device="cpu")
    model, _ = train_c3dpo(w[:5000], v[:5000], config, None, progress=False)
    pred, truth = predict_c3dpo(model, w[5000:], v[5000:]), camera[5000:].transpose(0, 2, 1)

    def error(p):  # mean point distance, the better depth sign per frame, relative to the shapes' size
        p = p - p.mean(axis=1, keepdims=True)
        flips = [np.linalg.norm(p * [1, 1, s] - truth, axis=2).mean(axis=1) for s in (1, -1)]
        return np.minimum(*flips).mean() / np.linalg.norm(truth, axis=2).mean()

    flat = error(truth * [1, 1, 0])
    assert flat > 0.45
    assert error(pred) < 0.2 * flat
