"""The shared alignment: convergence, the two linear solvers, and gradients vs finite differences."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nrsfm.procrustes import (align, align_vjp, apply_stationarity_jacobian, smoothed_nuclear_norm_and_gradient,
                              solve_stationarity, stationarity_jacobian, vee_antisym)


def _group(n, p=9, seed=0, batch=2):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(1, 1, 3, p, generator=g, dtype=torch.float64) + 0.3 * torch.randn(batch, n, 3, p, generator=g,
                                                                                       dtype=torch.float64)
    rot = torch.tensor(Rotation.random(batch * n, random_state=seed).as_matrix()).reshape(batch, n, 3, 3)
    return rot @ x + torch.randn(batch, n, 3, 1, generator=g, dtype=torch.float64)


def test_alignment_recovers_rotations_of_a_rigid_shape():
    shape = torch.randn(1, 1, 3, 8, dtype=torch.float64)
    rot = torch.tensor(Rotation.random(5, random_state=3).as_matrix())[None]
    al = align(rot @ shape)
    assert al.converged
    z = al.aligned[0]
    torch.testing.assert_close(z, z[:1].expand_as(z), atol=1e-9, rtol=0)  # all frames identical after alignment
    np.testing.assert_allclose(torch.linalg.det(al.rotations).numpy(), 1.0)


@pytest.mark.parametrize("n", [2, 4, 32])
def test_newton_alignment_reaches_the_sweep_fixed_point_in_fewer_steps(n):
    x = _group(n, seed=10 + n)
    sweeps = align(x, newton=False, max_iter=2000, tol=1e-13)
    fast = align(x, newton=True, tol=1e-13)
    assert sweeps.converged and fast.converged
    assert fast.iterations <= sweeps.iterations

    def spread(al):  # the GPA cost, invariant to the gauge (a common rotation)
        z = al.aligned
        return ((z - z.mean(dim=1, keepdim=True)) ** 2).sum((1, 2, 3))

    torch.testing.assert_close(spread(fast), spread(sweeps), rtol=1e-10, atol=0)
    # same aligned shapes up to one common rotation per group: the pairwise inner products agree
    g_fast = torch.einsum("bnap,bmaq->bnmpq", fast.aligned, fast.aligned)
    g_sweep = torch.einsum("bnap,bmaq->bnmpq", sweeps.aligned, sweeps.aligned)
    torch.testing.assert_close(g_fast, g_sweep, atol=1e-8, rtol=0)
    stationarity = vee_antisym(fast.aligned @ fast.aligned.sum(1, keepdim=True).transpose(-1, -2))
    assert stationarity.abs().max() < 1e-9


@pytest.mark.parametrize("n", [3, 20, 80])
def test_woodbury_solve_matches_dense(n):
    z = align(_group(n, seed=n)).aligned
    rhs = torch.randn(2, n, 3, dtype=torch.float64)
    a = solve_stationarity(z, rhs, method="dense")
    b = solve_stationarity(z, rhs, method="woodbury")
    torch.testing.assert_close(a, b, atol=1e-10 * a.abs().max().item(), rtol=1e-8)
    jac = stationarity_jacobian(z)
    torch.testing.assert_close(jac, jac.transpose(-1, -2), atol=1e-8 * jac.abs().max().item(), rtol=0)
    # the matrix-free operator applied to the solution gives the right-hand side back
    torch.testing.assert_close(apply_stationarity_jacobian(z, b), rhs, atol=1e-8, rtol=1e-8)


@pytest.mark.parametrize("method", ["dense", "woodbury"])
def test_smoothed_nuclear_gradient_matches_finite_differences(method, central_differences):
    x = _group(6, p=7, seed=4, batch=1)

    def value(x):
        return smoothed_nuclear_norm_and_gradient(align(x).aligned, 0.05)[0].sum().item()

    al = align(x)
    grad = align_vjp(smoothed_nuclear_norm_and_gradient(al.aligned, 0.05)[1], al, method=method)
    fd = central_differences(value, x)
    torch.testing.assert_close(grad, fd, atol=1e-6, rtol=1e-5)
