"""EM-PND (Lee et al.)."""

import numpy as np
import pytest

from nrsfm import SolverError, ValidationError, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d
from nrsfm.solvers import get_solver, params_from_strings


# ------------------------------------------------------------------ EM-PND (PND2) and EM-PPCA
def test_empnd_recovers_a_noise_free_low_rank_sequence():
    seq = lowrank_sequence(200, 30, 3, seed=0)
    rec = solve(seq, "empnd")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert np.isfinite(rec.rotations).all() and rec.iterations >= 2


def test_empnd_starts_from_another_solver():
    seq = lowrank_sequence(60, 15, 2, seed=3)
    for init in ("spm", "pr"):
        rec = solve(seq, "empnd", init=init)
        assert rec.info["init"] == init and e3d(rec.points_3d, seq.points_3d) < 1e-3, init
    with pytest.raises(ValidationError, match="init='spm' needs every point visible"):
        solve(lowrank_sequence(30, 10, 2, seed=0, missing=0.1), "empnd", init="spm")
    with pytest.raises(ValidationError, match="init: expected one of"):
        solve(seq, "empnd", init="c3dpo")


def test_empnd_with_missing_points_and_degenerate_frames():
    seq = lowrank_sequence(120, 25, 2, seed=2, missing=0.2)
    rec = solve(seq, "empnd")
    assert e3d(rec.points_3d, seq.points_3d) < 0.02
    vis = np.ones((10, 8))
    vis[3, :6] = 0
    with pytest.raises(SolverError, match="frame 3 has fewer than 3 visible points"):
        solve(lowrank_sequence(10, 8, 2, seed=0).replace(visibility=vis), "empnd")
    three = solve(lowrank_sequence(3, 10, 2, seed=0), "empnd", max_iter=20)
    assert np.isfinite(three.points_3d).all()


def test_empnd_cuts_the_csf2_start_short_with_missing_points(monkeypatch):
    import nrsfm.solvers.empnd as empnd

    seen = {}

    def start(seq, k, **overrides):
        seen.update(overrides, K=k)
        return seq.points_3d + 0.01

    monkeypatch.setattr(empnd, "csf2_start", start)
    seq = lowrank_sequence(60, 12, 2, seed=4, missing=0.1)
    solve(seq, "empnd", init_rounds=7, init_K=2, max_iter=3)
    assert seen == {"camera_rounds": 7, "round_iter": 5, "round_iter_alt": 0, "K": 2}
    with pytest.raises(ValidationError, match="init_rounds: expected >= 0, got -1"):
        solve(seq, "empnd", init_rounds=-1)


def test_pick_device_refuses_unknown_names_and_absent_gpus():
    import torch

    from nrsfm.device import pick_device

    assert pick_device("cpu").type == "cpu"
    assert pick_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValidationError, match="expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'tpu'"):
        pick_device("tpu")
    with pytest.raises(ValidationError, match="expected 'auto', 'cpu'"):
        pick_device("meta")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ValidationError, match="asked for, but torch sees"):
        pick_device(f"cuda:{count}" if count else "cuda")
    with pytest.raises(ValidationError, match="asked for, but torch sees"):  # refused before any work
        params_from_strings(get_solver("empnd").params, [f"device=cuda:{count}" if count else "device=cuda"])


def test_empnd_runs_where_it_is_asked_and_says_so():
    import torch

    seq = lowrank_sequence(60, 12, 2, seed=4, missing=0.1)
    cpu = solve(seq, "empnd", device="cpu", max_iter=15)
    assert cpu.info["device"] == "cpu" and cpu.info["start_s"] > 0
    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU here: the GPU half of this test needs one")
    for complete in (False, True):  # DensePosterior and CompletePosterior
        s = seq.replace(visibility=np.ones_like(seq.weights)) if complete else seq
        a = solve(s, "empnd", device="cpu", max_iter=15)
        b = solve(s, "empnd", device="cuda", max_iter=15)
        assert b.info["device"].startswith("cuda") and b.iterations == a.iterations
        np.testing.assert_allclose(b.points_3d, a.points_3d, atol=1e-6 * np.abs(a.points_3d).max())


def test_empnd_probe_keeps_the_start_with_the_lower_cost():
    seq = lowrank_sequence(60, 12, 2, seed=6)
    rec = solve(seq, "empnd", probe_iter=5, max_iter=30)
    costs = rec.info["probe_costs"]
    assert len(costs) == 2 and rec.info["init"] == ("factorisation", "csf2")[int(np.argmin(costs))]
    assert np.isfinite(rec.points_3d).all() and rec.iterations <= 30
    assert solve(seq, "empnd", max_iter=3, probe_iter=0).info["init"] == "factorisation"
    with pytest.raises(ValidationError, match="needs every point visible"):
        solve(lowrank_sequence(20, 10, 2, seed=0, missing=0.2), "empnd", init="factorisation")


def test_empnd_probes_both_starts_on_noise_free_tracks_only():
    from nrsfm.solvers.empnd import exactly_low_rank

    # a camera turning steadily about one axis: the factorisation start alone ends at e3D .086
    smooth = lowrank_sequence(300, 20, 3, cameras="smooth", seed=0)
    assert exactly_low_rank(smooth)
    rec = solve(smooth, "empnd")
    assert rec.info["probe_costs"] is not None and rec.info["init"] == "csf2"
    assert e3d(rec.points_3d, smooth.points_3d) < 0.02
    noisy = lowrank_sequence(40, 12, 2, seed=1, noise=1e-3)
    assert not exactly_low_rank(noisy)
    rec = solve(noisy, "empnd", max_iter=5)
    assert rec.info["probe_costs"] is None and rec.info["init"] == "factorisation"


def _pnd_problem(rng, n: int, q: int, spread: float):
    """A random EM-PND state: mean `(3, q)`, alignment, a precision with the PND null space, complete data."""
    import torch

    from nrsfm.solvers.empnd import align, constrained_directions

    mu0 = torch.from_numpy(rng.standard_normal((1, 3, q)) + spread * rng.standard_normal((n, 3, q)))
    mean = mu0.mean(dim=0)
    mean = mean / mean.norm()
    sr, s = align(mu0, mean)
    nb = constrained_directions(mean)
    proj = torch.eye(3 * q, dtype=torch.float64) - nb @ nb.T
    a = torch.from_numpy(rng.standard_normal((3 * q, 3 * q)))
    data = torch.from_numpy(rng.standard_normal((n, 3, q)))
    data[:, 2] = 0.0
    obs = torch.eye(q, dtype=torch.float64).expand(n, q, q).contiguous()
    return mean, sr, s, proj @ (a @ a.T) @ proj, data, obs


def test_pnd_cost_gradient_matches_finite_differences():
    import torch

    from nrsfm.solvers.empnd import DensePosterior, pnd_cost

    rng = np.random.default_rng(0)
    mean, sr, s, lam, data, obs = _pnd_problem(rng, 12, 6, 0.2)
    post = DensePosterior(lam, sr, data, obs, 1e-2)
    m_var = mean.clone().requires_grad_(True)
    cost, _ = pnd_cost(m_var, post.mu, post.moment)
    (grad,) = torch.autograd.grad(cost, m_var)
    direction = torch.from_numpy(rng.standard_normal(mean.shape))
    eps = 1e-6
    with torch.no_grad():
        fd = (pnd_cost(mean + eps * direction, post.mu, post.moment)[0]
              - pnd_cost(mean - eps * direction, post.mu, post.moment)[0]) / (2 * eps)
    assert abs(float(fd) - float((grad * direction).sum())) < 1e-6 * max(1.0, abs(float(fd)))


def test_empnd_complete_posterior_matches_the_dense_one():
    import torch

    from nrsfm.solvers.empnd import CompletePosterior, DensePosterior, align

    rng = np.random.default_rng(1)
    mean, sr, s, lam, data, obs = _pnd_problem(rng, 15, 7, 0.1)
    dense, fast = DensePosterior(lam, sr, data, obs, 1e-3), CompletePosterior(lam, sr, s, data, 1e-3)
    torch.testing.assert_close(fast.mu, dense.mu, rtol=1e-9, atol=1e-9)
    assert abs(fast.trace - dense.trace) < 1e-9 * dense.trace
    sr2, _ = align(dense.mu, mean + 0.05 * torch.from_numpy(rng.standard_normal(mean.shape)))
    torch.testing.assert_close(fast.moment(sr2), dense.moment(sr2), rtol=1e-9, atol=1e-9)


def test_empnd_rotated_block_sum_from_six_blocks_matches_the_kronecker_sum():
    import torch

    from nrsfm.solvers.empnd import _rotated_block_sum, _upper_blocks, _upper_gram_blocks

    rng = np.random.default_rng(2)
    n, q = 7, 5
    factor = torch.from_numpy(rng.standard_normal((n, q + 1, 3 * q)))
    mats = factor.transpose(1, 2) @ factor  # (F, 3q, 3q) symmetric
    rot = torch.from_numpy(rng.standard_normal((n, 3, 3)))  # any 3x3, not only rotations
    kron = torch.stack([torch.kron(r, torch.eye(q, dtype=torch.float64)) for r in rot])
    expected = (kron @ mats @ kron.transpose(1, 2)).sum(dim=0)
    torch.testing.assert_close(_rotated_block_sum(rot, _upper_blocks(mats, q), q), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(_upper_gram_blocks(factor, q), _upper_blocks(mats, q), rtol=1e-12, atol=1e-12)
