"""The Procrustean-regression (PR) loss of PRN (paper eq. 3-15) with its analytic backward pass.

For a group of ``n`` predicted shapes ``X_i`` `(3, P)` with 2D observations
``U_i`` `(2, P)` and weights ``W_i`` `(P,)` in [0, 1]::

    J = sum_i 1/2 ||(U_i - P_o X_i) * W_i||_F^2  +  lambda ||[vec(Z_1) ... vec(Z_n)]||_*

with ``Z_i`` the Procrustes-aligned centred shapes (:mod:`nrsfm.procrustes`,
the same code as the classical PR solver). A batch is split into groups and
the group losses are summed. The backward pass is analytic: the data term's
gradient (eq. 13), the nuclear norm's explicit subgradient (eq. 15) pulled
back through the alignment by :func:`nrsfm.procrustes.align_vjp` (eq. 5-11,
matrix-free), never through torch's SVD. Both the returned cost and the
gradient are ``f + lambda g`` (the official code returned ``f / lambda + g``
with the gradient of ``f + lambda g``; we keep them consistent).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nrsfm.errors import ValidationError, shape_error
from nrsfm.procrustes import align, align_vjp, nuclear_norm_and_subgradient


@dataclass
class PRLossParts:
    """Detached values of the last evaluation: data term, nuclear norm (both summed over groups),
    alignment steps (sweeps plus Newton steps) and whether every alignment converged."""

    data: float = 0.0
    nuclear: float = 0.0
    align_iterations: int = 0
    align_converged: bool = True


class _PRLossFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, u, w, lam, parts, align_device):  # x (B, n, 3, P), u (B, n, 2, P), w (B, n, P)
        w2 = (w * w).unsqueeze(2)  # (B, n, 1, P)
        resid = x[:, :, :2].detach() - u  # (B, n, 2, P)
        data = 0.5 * (resid * resid * w2).sum()
        ctx.lam = lam
        ctx.shape = x.shape
        if lam == 0:  # PRN w/o reg: the alignment would not enter the cost or the gradient
            ctx.save_for_backward(resid, w2)
            if parts is not None:
                parts.data, parts.nuclear = float(data), float("nan")
                parts.align_iterations, parts.align_converged = 0, True
            return data
        al = align(x.detach().to(align_device))
        nuc, sub = nuclear_norm_and_subgradient(al.aligned)
        nuc = nuc.to(x.device)
        ctx.save_for_backward(resid, w2, sub)
        ctx.al = al
        if parts is not None:
            parts.data, parts.nuclear = float(data), float(nuc.sum())
            parts.align_iterations, parts.align_converged = al.iterations, al.converged
        return data + lam * nuc.sum()

    @staticmethod
    def backward(ctx, grad_out):
        resid, w2 = ctx.saved_tensors[:2]
        grad = resid.new_zeros(ctx.shape)
        grad[:, :, :2] = resid * w2  # eq. 13
        if ctx.lam != 0:
            grad = grad + ctx.lam * align_vjp(ctx.saved_tensors[2], ctx.al).to(grad.device)  # eq. 5-11 and 15
        return grad_out * grad, None, None, None, None, None


def pr_loss(pred: torch.Tensor, points_2d: torch.Tensor, weights: torch.Tensor | None = None, *,
            lam: float = 0.05, group_size: int | None = None, parts: PRLossParts | None = None,
            align_device: str | torch.device | None = None) -> torch.Tensor:
    """The PR loss summed over groups.

    Args:
        pred: `(N, P, 3)` predicted shapes (frame-major, coordinates last), N = groups x group_size.
        points_2d: `(N, P, 2)` observations (orthographic; same normalisation as ``pred``).
        weights: `(N, P)` in [0, 1] (0 = missing), or None for all ones.
        lam: regularisation weight lambda (0 = PRN without regularisation).
        group_size: frames per group (default: one group of N frames).
        parts: optional :class:`PRLossParts` filled with the last evaluation's terms.
        align_device: where the alignment, the nuclear norm and their backward pass run (None: on
            ``pred``'s device). ``"cpu"`` moves them off a GPU, where these small decompositions are
            latency-bound (see ``benchmarks/RESULTS.md``, PRN loss speed).

    Returns:
        A scalar tensor whose backward pass is the analytic PR gradient.
    """
    if pred.ndim != 3 or pred.shape[-1] != 3:
        raise shape_error("pred", "(N, P, 3)", tuple(pred.shape))
    n_total, n_points, _ = pred.shape
    if points_2d.shape != (n_total, n_points, 2):
        raise shape_error("points_2d", f"(N, P, 2) = ({n_total}, {n_points}, 2)", tuple(points_2d.shape))
    g = n_total if group_size is None else group_size
    if g < 2 or n_total % g:
        raise ValidationError(f"group_size: expected a divisor of N = {n_total} that is at least 2, got {g}")
    if weights is None:
        weights = torch.ones(n_total, n_points, dtype=pred.dtype, device=pred.device)
    elif weights.shape != (n_total, n_points):
        raise shape_error("weights", f"(N, P) = ({n_total}, {n_points})", tuple(weights.shape))
    b = n_total // g
    x = pred.reshape(b, g, n_points, 3).transpose(-1, -2)  # (B, n, 3, P)
    u = points_2d.to(pred.dtype).reshape(b, g, n_points, 2).transpose(-1, -2)  # (B, n, 2, P)
    w = weights.to(pred.dtype).reshape(b, g, n_points)
    dev = pred.device if align_device is None else torch.device(align_device)
    return _PRLossFunction.apply(x, u, w, float(lam), parts, dev)


def regularizer(pred: torch.Tensor, group_size: int | None = None) -> torch.Tensor:
    """``sum over groups of ||Z~||_*`` for `(N, P, 3)` shapes (a detached value, for tests and logs)."""
    n_total, n_points, _ = pred.shape
    g = n_total if group_size is None else group_size
    x = pred.detach().reshape(n_total // g, g, n_points, 3).transpose(-1, -2)
    return nuclear_norm_and_subgradient(align(x).aligned)[0].sum()
