"""The rank-3 rectification of a rank-3K factorisation (EM-PND2's start)."""

import numpy as np
import pytest

from nrsfm import SolverError
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d


def test_factorisation_start_is_exact_on_a_rigid_object_and_keeps_the_tracks():
    from nrsfm.solvers.rectify import factor_rotations, factorisation_start

    rigid = lowrank_sequence(60, 15, 1, seed=3)
    start = factorisation_start(rigid.points_2d)
    assert e3d(start, rigid.points_3d) < 1e-8  # rigid: the trace-minimising depths are the true ones
    w = rigid.points_2d - rigid.points_2d.mean(axis=1, keepdims=True)
    np.testing.assert_allclose(start[..., :2], w, atol=1e-10)
    with pytest.raises(SolverError, match="every track is constant"):
        factorisation_start(np.zeros((5, 6, 2)))
    # the recovered camera rows are the true ones up to one global orthogonal matrix and a sign per frame:
    # their inner products with frame 0's rows agree up to that sign
    rot, scale, k = factor_rotations(w.transpose(0, 2, 1).reshape(-1, 15))
    assert k == 3 and scale.min() == 1.0
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-10)
    est, true = rot[:, :, :2].transpose(0, 2, 1), rigid.camera_rotations[:, :2]  # (F, 2, 3)
    e0, t0 = est @ est[0].T, true @ true[0].T
    sign = np.sign(np.einsum("fij,fij->f", e0, t0))
    np.testing.assert_allclose(e0, sign[:, None, None] * t0, atol=1e-8)


def test_rank3_rectification_drives_the_orthonormality_residual_down():
    from nrsfm.solvers.rectify import OrthonormalityConstraints, rectify_fista, rectify_rank

    seq = lowrank_sequence(40, 12, 2, seed=5)
    w = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    u = np.linalg.svd(w.transpose(0, 2, 1).reshape(-1, 12), full_matrices=False)[0]
    con3 = OrthonormalityConstraints(u[:, :3])
    _, g = rectify_fista(con3, np.eye(3) / 3)
    con6 = OrthonormalityConstraints(u[:, :6])
    start = np.zeros((6, 3))
    start[:3, : g.shape[1]] = g
    before = con6.cost(start @ start.T / np.linalg.norm(start) ** 2)[0]
    gg, g6 = rectify_rank(con6, start, max_iter=5000)
    assert con6.cost(gg)[0] < 1e-5 * before and g6.shape == (6, 3)
    assert abs(np.trace(gg) - 1) < 1e-12 and np.linalg.eigvalsh(gg).min() > -1e-12


@pytest.mark.parametrize("k", [5, 8])  # 10 frames: K^2 = 25 <= 4F uses the Gram matrix, 64 > 4F the factor
def test_orthonormality_constraints_gram_form_equals_the_direct_residual(k):
    import torch

    from nrsfm.solvers.rectify import OrthonormalityConstraints

    u3 = np.linalg.qr(np.random.default_rng(0).standard_normal((20, k)))[0]
    con = OrthonormalityConstraints(u3)
    assert (con._factor is None) == (k == 5)
    gg = np.random.default_rng(1).standard_normal((k, k))
    gg = gg @ gg.T
    a, b = u3[0::2], u3[1::2]
    direct = np.concatenate([np.einsum("fi,ij,fj->f", a, gg, a) - np.einsum("fi,ij,fj->f", b, gg, b),
                             2 * np.einsum("fi,ij,fj->f", a, gg, b)])
    cost, half_grad = con.cost(gg)
    assert abs(cost * con.lipschitz - direct @ direct) < 1e-9 * (direct @ direct)
    g_t = torch.from_numpy(gg).requires_grad_(True)
    at, bt = torch.from_numpy(a), torch.from_numpy(b)
    res = torch.cat([((at @ g_t) * at).sum(1) - ((bt @ g_t) * bt).sum(1), 2 * ((at @ g_t) * bt).sum(1)])
    (grad,) = torch.autograd.grad((res**2).sum(), g_t)  # over symmetric GG: its symmetric part
    np.testing.assert_allclose(2 * half_grad * con.lipschitz, (grad + grad.T).numpy() / 2, rtol=1e-9, atol=1e-12)
    # the scale is the largest eigenvalue of E^T E: a power iteration gets no higher
    x = np.random.default_rng(2).standard_normal(k * k)
    for _ in range(200):
        x = con.cost(x.reshape(k, k))[1].ravel()
        x /= np.linalg.norm(x)
    assert abs(float(con.cost(x.reshape(k, k))[0]) - 1.0) < 1e-6


def test_unit_trace_psd_projection():
    from nrsfm.solvers.rectify import project_unit_trace_psd

    gg, g = project_unit_trace_psd(np.diag([3.0, 1.0, 0.5, -1.0]))
    np.testing.assert_allclose(np.diag(gg), [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    gg, g = project_unit_trace_psd(np.diag([0.5, 0.4, 0.3, 0.2]), rank=3)
    np.testing.assert_allclose(np.sort(np.diag(gg))[::-1], [0.4333333333, 0.3333333333, 0.2333333333, 0.0],
                               atol=1e-9)
    assert g.shape == (4, 3) and abs(np.trace(gg) - 1) < 1e-12
    m = 0.05 * np.random.default_rng(0).normal(size=(9, 9))  # the rank-3 projection keeps the top eigenvectors
    vec = np.linalg.eigh((m + m.T) / 2)[1][:, -3:]
    gg, g = project_unit_trace_psd(m, rank=3)
    np.testing.assert_allclose(vec @ (vec.T @ gg @ vec) @ vec.T, gg, atol=1e-12)
    assert g.shape == (9, 3) and abs(np.trace(gg) - 1) < 1e-12
    with pytest.raises(SolverError, match="non-finite"):
        project_unit_trace_psd(np.full((5, 5), np.nan), rank=3)
