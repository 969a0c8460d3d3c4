"""Generalised Procrustes alignment (no scale) and its analytic gradient.

This module is the one home of the alignment used by the classical PR solver
(:mod:`nrsfm.solvers.pr`) and by the PRN loss (:mod:`prn.loss`).

Model (PRN paper eq. 4): for shapes ``X_i`` `(3, P)`, ``i = 1..n``, with
centred versions ``Y_i = X_i T``, find proper rotations ``R_i`` minimising
``sum_i ||R_i Y_i - mean_j R_j Y_j||^2``; the aligned shapes are
``Z_i = R_i Y_i``.

Gradient (PRN eq. 5-11, derived here in an equivalent matrix-free form): at
the optimum every ``Z_i M^T`` is symmetric, with ``M = sum_j Z_j``. A
perturbation ``dY_i`` (written in the aligned frame, ``dY'_i = R_i dY_i``)
moves the rotations by infinitesimal rotations ``w_i`` solving ``J w = -K
dY'`` where ``J`` `(3n, 3n)` and ``K`` are the derivatives of the
stationarity conditions ``v(Z_i M^T) = 0`` (``v(A) = vee(A - A^T)``). ``J``
is singular along a common rotation of all shapes (the gauge; the paper's
matrix B): we add ``E^T E`` with ``E = [I3 ... I3]``, which fixes
``sum_i w_i = 0`` and leaves the solution of the consistent system
unchanged. For an upstream gradient ``G_i = dL/dZ_i`` the vector-Jacobian
product is::

    h_i  = v(G_i Z_i^T)                      (3n,)
    mu   = (J + E^T E)^{-T} h
    dL/dY'_j = G_j - ([mu_j]_x M - sum_i [mu_i]_x Z_i)
    dL/dX_j  = R_j^T dL/dY'_j  T             (T removes the centroid)

Nothing of size ``3nP x 3nP`` is ever formed: ``J`` is `(3n, 3n)` per group
and everything else is batched products. Shapes carry a leading batch
(group) dimension ``B``: ``X`` is `(B, n, 3, P)`.
"""

from __future__ import annotations

from dataclasses import dataclass

from nrsfm.geometry import nearest_rotation


_EPS_CACHE: dict = {}


def _torch():
    import torch

    return torch


def _levi_civita(like):
    torch = _torch()
    key = (like.dtype, like.device)
    if key not in _EPS_CACHE:
        eps = torch.zeros(3, 3, 3, dtype=like.dtype, device=like.device)
        for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
            eps[a, b, c] = 1.0
            eps[b, a, c] = -1.0
        _EPS_CACHE[key] = eps
    return _EPS_CACHE[key]


def skew(w):
    """`(..., 3)` vectors -> `(..., 3, 3)` cross-product matrices ``[w]_x``."""
    torch = _torch()
    z = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([z, -w[..., 2], w[..., 1]], -1),
                        torch.stack([w[..., 2], z, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def vee_antisym(a):
    """``v(A) = vee(A - A^T)`` for `(..., 3, 3)` A; ``w . v(A) = <[w]_x, A>``."""
    torch = _torch()
    return torch.stack([a[..., 2, 1] - a[..., 1, 2], a[..., 0, 2] - a[..., 2, 0], a[..., 1, 0] - a[..., 0, 1]], -1)


@dataclass
class Alignment:
    """Result of :func:`align`.

    Attributes:
        aligned: `(B, n, 3, P)` aligned centred shapes ``Z_i = R_i Y_i``.
        rotations: `(B, n, 3, 3)` proper rotations ``R_i``.
        centred: `(B, n, 3, P)` centred inputs ``Y_i``.
        iterations: alignment sweeps run; converged: whether the rotation
            change fell below the tolerance.
    """

    aligned: object
    rotations: object
    centred: object
    iterations: int
    converged: bool


def proper_procrustes(target, source):
    """Rotations `(..., 3, 3)` with det +1 maximising ``tr(R source target^T)``."""
    return nearest_rotation(target @ source.transpose(-1, -2))  # (..., 3, 3)


def rotation_exp(w):
    """Rodrigues: `(..., 3)` rotation vectors -> `(..., 3, 3)` rotations ``exp([w]_x)``."""
    torch = _torch()
    th2 = (w * w).sum(-1)[..., None, None]
    th = th2.sqrt()
    small = th2 < 1e-8
    a = torch.where(small, 1 - th2 / 6, torch.sin(th) / th.clamp_min(1e-30))
    b = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2.clamp_min(1e-30))
    k = skew(w)
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * k + b * (k @ k)


def align(x, *, tol: float | None = None, max_iter: int = 200, init=None, newton: bool | None = None,
          newton_below: float = 0.3) -> Alignment:
    """Generalised Procrustes alignment without scale to the mean of the aligned shapes.

    The classic fixed-point sweep (every ``R_i`` = proper Procrustes rotation
    of ``Y_i`` onto the current mean) converges linearly, often slowly (tens
    of sweeps). Once a sweep moves the rotations by less than
    ``newton_below``, Newton steps on the stationarity conditions take over:
    ``(J + E^T E) w = -v(Z_i M^T)``, ``R_i <- exp([w_i]_x) R_i``, with J the
    matrix of :func:`stationarity_jacobian` (also the backward pass's). A step
    is only taken where the Cholesky factorisation succeeds (J positive
    definite: near a minimum, not a saddle); convergence is always confirmed
    by a final fixed-point sweep that moves the rotations by less than
    ``tol``, so the result is the same fixed point as sweeping alone, reached
    in a few quadratic steps.

    Args:
        x: `(B, n, 3, P)` shapes (torch tensor; any float dtype/device).
        tol: stop when the largest rotation change (Frobenius) of a sweep is
            below this (default 1e-10 for float64, 1e-5 for float32).
        max_iter: sweeps plus Newton steps at most.
        init: optional `(B, n, 3, 3)` starting rotations (warm start).
        newton: use the Newton steps (``False``: sweeps only); default: when
            ``n <= 64`` (the dense `(3n, 3n)` factorisation is cheap there; long
            sequences are aligned warm-started by the PR solver, where sweeps
            are few).
        newton_below: sweep change under which Newton steps start.

    Returns:
        :class:`Alignment`. The gauge (a common rotation) is fixed by making
        the mean shape's rotation to the first shape's frame the identity at
        the start; it does not affect rotation-invariant losses.
    """
    torch = _torch()
    if tol is None:
        tol = 1e-10 if x.dtype == torch.float64 else 1e-5
    with torch.no_grad():
        y = x - x.mean(dim=-1, keepdim=True)
        b, n = y.shape[:2]
        if newton is None:
            newton = n <= 64
        rot = proper_procrustes(y[:, :1], y) if init is None else init  # start: every shape onto the first
        converged = False
        use_newton = False
        it = 0
        for it in range(1, max_iter + 1):
            if use_newton:
                z = rot @ y
                resid = vee_antisym(z @ z.sum(dim=1, keepdim=True).transpose(-1, -2))  # (B, n, 3)
                chol, info = torch.linalg.cholesky_ex(stationarity_jacobian(z))
                if bool((info == 0).all()):
                    step = -torch.cholesky_solve(resid.reshape(b, 3 * n, 1), chol).reshape(b, n, 3)
                    size = step.norm(dim=-1).max()
                    if size < 0.5:  # a trusted local step; otherwise fall back to a sweep
                        rot = rotation_exp(step) @ rot
                        if size >= tol:
                            continue
                use_newton = False  # converged, not positive definite or too long: confirm / continue by a sweep
                continue
            mean = (rot @ y).mean(dim=1, keepdim=True)  # (B, 1, 3, P)
            new = proper_procrustes(mean, y)
            change = (new - rot).flatten(-2).norm(dim=-1).max()
            rot = new
            if change < tol:
                converged = True
                break
            use_newton = newton and bool(change < newton_below)
        return Alignment(aligned=rot @ y, rotations=rot, centred=y, iterations=it, converged=converged)


def stationarity_jacobian(z):
    """The gauge-fixed `(B, 3n, 3n)` matrix ``J + E^T E`` for aligned shapes ``z`` `(B, n, 3, P)`.

    ``J w`` is the change of the stationarity conditions ``v(Z_i M^T)`` under
    infinitesimal rotations ``Z_i -> (I + [w_i]_x) Z_i``. With the identity
    ``eps_abc eps_ade = d_bd d_ce - d_be d_cd`` its blocks are::

        J_ij = d_ij (tr(K_i) I - K_i) + Z_j Z_i^T - tr(Z_i Z_j^T) I,   K_i = Z_i M^T

    built from one `(3n, 3n)` Gram product and in-place edits of its diagonals.
    ``J + E^T E`` is symmetric positive definite at a (non-degenerate) GPA minimum.
    """
    torch = _torch()
    b, n, _, p = z.shape
    flat = z.reshape(b, 3 * n, p)
    gram = (flat @ flat.transpose(-1, -2)).view(b, n, 3, n, 3)  # [i, a, j, d] = (Z_i Z_j^T)_ad
    jac = gram.transpose(2, 4).contiguous()  # [i, c, j, e] = (Z_j Z_i^T)_ce (the Gram matrix is symmetric)
    traces = torch.diagonal(jac, dim1=2, dim2=4)  # (B, n, n, 3) view
    traces -= traces.sum(-1, keepdim=True) - 1.0  # - tr(Z_i Z_j^T) I, + I from the gauge E^T E
    blocks = torch.diagonal(jac, dim1=1, dim2=3)  # (B, 3, 3, n) view of the diagonal blocks
    blocks += _diagonal_blocks_from_k(gram.sum(3)).permute(0, 2, 3, 1)  # K_i = Z_i M^T = sum_j Z_i Z_j^T
    return jac.view(b, 3 * n, 3 * n)


def apply_stationarity_jacobian(z, w):
    """``(J + E^T E) w`` without forming J: `(B, n, 3, P)` shapes, `(B, n, 3)` -> `(B, n, 3)`; O(nP)."""
    m = z.sum(dim=1, keepdim=True)  # (B, 1, 3, P)
    sw = skew(w)  # (B, n, 3, 3)
    diag = vee_antisym(sw @ z @ m.transpose(-1, -2))  # v([w_i] Z_i M^T)
    s = (sw @ z).sum(dim=1, keepdim=True)  # (B, 1, 3, P)  sum_j [w_j] Z_j
    coup = vee_antisym(z @ s.transpose(-1, -2))  # v(Z_i S^T)
    return diag + coup + w.sum(dim=1, keepdim=True)


def _diagonal_blocks_from_k(k):
    """``tr(K_i) I - K_i`` `(B, n, 3, 3)` for ``K_i = Z_i M^T``: the part of J's diagonal blocks from
    ``v([w_i]_x Z_i M^T)`` alone (no coupling, no gauge)."""
    torch = _torch()
    eye = torch.eye(3, dtype=k.dtype, device=k.device)
    return torch.diagonal(k, dim1=-2, dim2=-1).sum(-1)[..., None, None] * eye - k


def _diagonal_blocks(z):
    """:func:`_diagonal_blocks_from_k` for aligned shapes ``z`` `(B, n, 3, P)`."""
    return _diagonal_blocks_from_k(z @ z.sum(dim=1, keepdim=True).transpose(-1, -2))


def solve_stationarity(z, rhs, *, method: str = "auto"):
    """Solve ``(J + E^T E) x = rhs`` for `(B, n, 3)` rhs (J is symmetric at a converged alignment).

    ``method``: ``"dense"`` assembles the `(3n, 3n)` matrix (small groups);
    ``"woodbury"`` uses ``J + E^T E = blockdiag(A_i) + U V^T`` with the
    coupling ``v(Z_i (sum_j [w_j]_x Z_j)^T)`` of rank <= 3P and the gauge of
    rank 3, an exact O(n P^2) solve for long sequences; ``"auto"`` picks
    dense up to n = 64.
    """
    torch = _torch()
    b, n, _, p = z.shape
    if method == "auto":
        method = "dense" if n <= 64 else "woodbury"
    if method == "dense":
        jac = stationarity_jacobian(z)
        return torch.linalg.solve(jac.transpose(-1, -2), rhs.reshape(b, 3 * n, 1)).reshape(b, n, 3)
    if method != "woodbury":
        raise ValueError(f"method: expected 'auto', 'dense' or 'woodbury', got {method!r}")
    eps = _levi_civita(z)
    d_inv = torch.linalg.inv(_diagonal_blocks(z))  # (B, n, 3, 3)
    # coupling = C Q:  C[(i,c),(b,p)] = -eps_abc Z_i,ap ;  Q[(b,p),(j,e)] = -eps_bde Z_j,dp
    c_mat = -torch.einsum("abc,xiap->xicbp", eps, z).reshape(b, n, 3, 3 * p)
    q_mat = -torch.einsum("bde,xjdp->xbpje", eps, z).reshape(b, 3 * p, n, 3)
    eye3 = torch.eye(3, dtype=z.dtype, device=z.device).expand(b, n, 3, 3)
    u = torch.cat([c_mat, eye3], dim=-1)  # (B, n, 3, r)  r = 3P + 3
    vt = torch.cat([q_mat, eye3.permute(0, 2, 1, 3)], dim=1)  # (B, r, n, 3)
    # the system is symmetric, so solving J x = rhs and J^T x = rhs agree; we solve J^T x = rhs:
    # J^T = D^T + V U^T  ->  Woodbury with D^T, V, U
    dt_inv = d_inv.transpose(-1, -2)
    v_mat = vt.permute(0, 2, 3, 1)  # (B, n, 3, r)
    dinv_rhs = (dt_inv @ rhs.unsqueeze(-1)).squeeze(-1)  # (B, n, 3)
    dinv_v = dt_inv @ v_mat  # (B, n, 3, r)
    small = torch.eye(u.shape[-1], dtype=z.dtype, device=z.device) + torch.einsum("xnci,xncj->xij", u, dinv_v)
    t = torch.linalg.solve(small, torch.einsum("xnci,xnc->xi", u, dinv_rhs).unsqueeze(-1)).squeeze(-1)  # (B, r)
    return dinv_rhs - torch.einsum("xnci,xi->xnc", dinv_v, t)


def align_vjp(grad_aligned, al: Alignment, *, method: str = "auto"):
    """Backpropagate ``dL/dZ`` `(B, n, 3, P)` through the alignment to ``dL/dX`` `(B, n, 3, P)`.

    Exact at a converged alignment (see the module docstring). ``method``
    selects the linear solver (:func:`solve_stationarity`).
    """
    z, rot = al.aligned, al.rotations
    h = vee_antisym(grad_aligned @ z.transpose(-1, -2))  # (B, n, 3)
    mu = solve_stationarity(z, h, method=method)
    m = z.sum(dim=1, keepdim=True)  # (B, 1, 3, P)
    smu = skew(mu)  # (B, n, 3, 3)
    coupling = (smu @ z).sum(dim=1, keepdim=True)  # (B, 1, 3, P)
    g_prime = grad_aligned - (smu @ m - coupling)  # dL/dY' (B, n, 3, P)
    g = rot.transpose(-1, -2) @ g_prime  # dL/dY
    return g - g.mean(dim=-1, keepdim=True)  # T (centring) is symmetric


def nuclear_norm_and_subgradient(z):
    """``||Z~||_*`` and ``U sign(S) V^T`` for ``Z~ = [vec(Z_1) ... vec(Z_n)]`` `(3P, n)`.

    Args:
        z: `(B, n, 3, P)`.

    Returns:
        `(B,)` nuclear norms and the `(B, n, 3, P)` subgradient (computed
        explicitly from the SVD; nothing is backpropagated through it).
    """
    torch = _torch()
    b, n = z.shape[:2]
    mat = z.reshape(b, n, -1).transpose(1, 2)  # (B, 3P, n), columns vec(Z_i) (row-major vec; norm is unchanged)
    u, s, vt = torch.linalg.svd(mat, full_matrices=False)
    tol = s.amax(dim=-1, keepdim=True) * max(mat.shape[-2:]) * torch.finfo(z.dtype).eps
    sign = (s > tol).to(z.dtype)
    sub = (u * sign.unsqueeze(-2)) @ vt  # (B, 3P, n)
    return s.sum(dim=-1), sub.transpose(1, 2).reshape(z.shape)


def _spectral_function(z, value, derivative):
    """``sum_k value(s_k)`` over the singular values of ``Z~`` `(3P, n)` for `(B, n, 3, P)` ``z``, and its gradient
    ``U diag(derivative(s)) V^T`` reshaped like ``z``."""
    torch = _torch()
    b, n = z.shape[:2]
    mat = z.reshape(b, n, -1).transpose(1, 2)
    u, s, vt = torch.linalg.svd(mat, full_matrices=False)
    grad = (u * derivative(s).unsqueeze(-2)) @ vt
    return value(s).sum(dim=-1), grad.transpose(1, 2).reshape(z.shape)


def smoothed_nuclear_norm_and_gradient(z, smoothing: float):
    """``sum_k sqrt(s_k^2 + e^2)`` of ``Z~`` `(3P, n)` and its gradient ``U diag(s / sqrt(s^2 + e^2)) V^T``.

    A differentiable surrogate of the nuclear norm (``e = smoothing``, in the
    units of the singular values) used by the per-sequence PR solver.
    """
    e2 = smoothing * smoothing
    return _spectral_function(z, lambda s: (s * s + e2).sqrt(), lambda s: s / (s * s + e2).sqrt())


def log_det_and_gradient(z, offset: float):
    """``sum_k log sqrt(s_k^2 + d^2)`` of ``Z~`` `(3P, n)` and its gradient ``U diag(s / (s^2 + d^2)) V^T``.

    The log-determinant rank surrogate of the per-sequence PR solver (``d = offset``, in the units of the
    singular values).
    """
    d2 = offset * offset
    return _spectral_function(z, lambda s: 0.5 * (s * s + d2).log(), lambda s: s / (s * s + d2))
