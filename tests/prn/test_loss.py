"""The PR loss: analytic backward vs finite differences, vs autograd through an unrolled alignment,
and the regulariser's invariance to per-frame rotations."""

import pytest
import torch
from scipy.spatial.transform import Rotation

from nrsfm.errors import ValidationError
from prn.loss import PRLossParts, pr_loss, regularizer


def _shapes(n_frames, n_points=7, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(1, n_points, 3, generator=g, dtype=dtype)
    x = base + 0.3 * torch.randn(n_frames, n_points, 3, generator=g, dtype=dtype)
    rot = torch.tensor(Rotation.random(n_frames, random_state=seed).as_matrix(), dtype=dtype)
    x = x @ rot.transpose(-1, -2)
    u = x[..., :2] + 0.1 * torch.randn(n_frames, n_points, 2, generator=g, dtype=dtype)
    w = torch.rand(n_frames, n_points, generator=g, dtype=dtype)
    return x, u, w


@pytest.mark.parametrize("n_frames, group_size", [(4, 2), (6, 3), (8, 4), (6, 6)])
@pytest.mark.parametrize("weighted", [False, True])
def test_gradcheck_float64(n_frames, group_size, weighted):
    x, u, w = _shapes(n_frames, n_points=5, seed=n_frames + group_size)
    x.requires_grad_(True)
    fn = lambda x: pr_loss(x, u, w if weighted else None, lam=0.7, group_size=group_size)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (x,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_regularizer_unchanged_when_each_frame_is_rotated():
    x, _, _ = _shapes(10, seed=3)
    rot = torch.tensor(Rotation.random(10, random_state=9).as_matrix())
    before = regularizer(x, group_size=5)
    after = regularizer(x @ rot.transpose(-1, -2) + torch.randn(10, 1, 3, dtype=x.dtype), group_size=5)
    assert after.item() == pytest.approx(before.item(), rel=1e-9)
    # ...while the nuclear norm of the raw shapes does change
    raw = lambda s: torch.linalg.matrix_norm(s.reshape(10, -1).T, ord="nuc")  # noqa: E731
    assert abs(raw(x @ rot.transpose(-1, -2)) - raw(x)) > 1e-3


def _proper(h):
    u, _, vt = torch.linalg.svd(h)
    d = torch.sign(torch.linalg.det(u @ vt))
    u = torch.cat([u[..., :2], u[..., 2:] * d[..., None, None]], dim=-1)
    return u @ vt


def _autograd_reference(x, u, w, lam, iters=300):
    """Independent implementation: plain autograd through an unrolled Procrustes iteration and
    torch's differentiable nuclear norm (well-conditioned random case: distinct singular values)."""
    y = (x - x.mean(dim=1, keepdim=True)).transpose(-1, -2)  # (n, 3, P)
    rot = _proper(y[:1] @ y.transpose(-1, -2))
    for _ in range(iters):
        mean = (rot @ y).mean(dim=0, keepdim=True)
        rot = _proper(mean @ y.transpose(-1, -2))
    z = rot @ y
    nuc = torch.linalg.matrix_norm(z.reshape(z.shape[0], -1).T, ord="nuc")
    data = 0.5 * (((x[..., :2] - u) * w[..., None]) ** 2).sum()
    return data + lam * nuc


@pytest.mark.parametrize("n_frames", [3, 5])
def test_agrees_with_autograd_through_iterative_alignment(n_frames):
    x, u, w = _shapes(n_frames, n_points=6, seed=11)
    x1 = x.clone().requires_grad_(True)
    pr_loss(x1, u, w, lam=0.5).backward()
    x2 = x.clone().requires_grad_(True)
    _autograd_reference(x2, u, w, 0.5).backward()
    torch.testing.assert_close(x1.grad, x2.grad, atol=1e-7, rtol=1e-6)


def test_float32_and_parts():
    x, u, w = _shapes(8, seed=5, dtype=torch.float32)
    x.requires_grad_(True)
    parts = PRLossParts()
    loss = pr_loss(x, u, w, lam=0.05, group_size=4, parts=parts)
    loss.backward()
    assert x.grad.dtype == torch.float32 and torch.isfinite(x.grad).all()
    assert loss.item() == pytest.approx(parts.data + 0.05 * parts.nuclear, rel=1e-5)
    assert parts.align_converged


def test_lambda_zero_is_the_data_term_only():
    x, u, w = _shapes(6, seed=2)
    x.requires_grad_(True)
    pr_loss(x, u, w, lam=0.0, group_size=3).backward()
    expected = torch.zeros_like(x)
    expected[..., :2] = (x[..., :2] - u) * w[..., None] ** 2
    torch.testing.assert_close(x.grad, expected.detach())


def test_bad_shapes():
    x, u, w = _shapes(6)
    with pytest.raises(ValidationError, match="group_size"):
        pr_loss(x, u, group_size=4)
    with pytest.raises(ValidationError, match=r"points_2d: expected \(N, P, 2\)"):
        pr_loss(x, u[:5])


def test_pr_loss_align_device_gives_the_same_value_and_gradient():
    """``align_device`` only moves the computation: the value and the gradient are unchanged (the prediction
    lives on the GPU when there is one, so there the test crosses devices)."""
    device = "cuda" if torch.cuda.is_available() else "cpu"
    gen = torch.Generator().manual_seed(0)
    pred = torch.randn(8, 6, 3, generator=gen, dtype=torch.float64).to(device)
    obs = pred[..., :2].detach() + 0.1 * torch.randn(8, 6, 2, generator=gen, dtype=torch.float64).to(device)
    a = pred.clone().requires_grad_(True)
    b = pred.clone().requires_grad_(True)
    la = pr_loss(a, obs, lam=0.3, group_size=4)
    lb = pr_loss(b, obs, lam=0.3, group_size=4, align_device="cpu")
    la.backward()
    lb.backward()
    torch.testing.assert_close(la, lb)
    torch.testing.assert_close(a.grad, b.grad)
    assert a.grad.abs().sum() > 0
