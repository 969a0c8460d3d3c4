"""Small geometric helpers shared by the converters, solvers and metrics.

Rotations act on column vectors (``x = R X``); batches of rotations have
shape `(F, 3, 3)`.
"""

from __future__ import annotations

import numpy as np


def complete_rotation(rows: np.ndarray) -> np.ndarray:
    """Complete orthographic camera rows to proper rotations.

    Args:
        rows: `(F, 2, 3)` camera rows (assumed orthonormal, or nearly).

    Returns:
        `(F, 3, 3)` rotations whose first two rows are ``rows`` projected to
        the nearest pair of orthonormal rows and whose third row is their
        cross product (so det = +1).
    """
    rows = nearest_rotation(rows, allow_reflection=True)
    third = np.cross(rows[:, 0], rows[:, 1])
    return np.concatenate([rows, third[:, None, :]], axis=1)


def nearest_rotation(m, allow_reflection: bool = False):
    """The orthogonal polar factor ``U V^T`` of ``m = U S V^T``: the nearest matrices with orthonormal rows.

    The one polar decomposition of the package (cameras, Procrustes alignment, metrics); it takes numpy arrays
    and torch tensors (autograd passes through) alike.

    Args:
        m: `(..., n, 3)` matrices, n <= 3 (`(..., 2, 3)`: orthographic camera rows).
        allow_reflection: when False (square ``m`` only) the sign of the last singular direction is chosen so that
            det = +1: the nearest proper rotation.
    """
    if type(m).__module__.partition(".")[0] == "torch":
        import torch

        u, _, vt = torch.linalg.svd(m, full_matrices=False)
        r = u @ vt
        if allow_reflection:
            return r
        d = torch.sign(torch.linalg.det(r))
        d = torch.where(d == 0, torch.ones_like(d), d)
        return torch.cat([u[..., :-1], u[..., -1:] * d[..., None, None]], dim=-1) @ vt
    u, _, vt = np.linalg.svd(m, full_matrices=False)
    r = u @ vt
    if allow_reflection:
        return r
    d = np.sign(np.linalg.det(r))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, -1] *= d[..., None]
    return u @ vt


def centre(points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Subtract the per-frame centroid.

    Args:
        points: `(F, P, D)`.
        weights: optional `(F, P)`; the centroid is then the weighted mean
            (points with weight 0 do not move it).

    Returns:
        `(F, P, D)` centred points.
    """
    if weights is None:
        return points - points.mean(axis=1, keepdims=True)
    w = weights[..., None]
    denom = np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    return points - (points * w).sum(axis=1, keepdims=True) / denom


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """`(n, 3, 3)` rotations drawn uniformly (Haar) from SO(3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix()


def project_orthographic(points_3d: np.ndarray) -> np.ndarray:
    """`(F, P, 3)` camera-frame points -> `(F, P, 2)` orthographic projection."""
    return points_3d[..., :2].copy()


def project_perspective(points_3d: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Pinhole projection ``uv = f * Xc[:2] / Xc[2] + c``.

    Args:
        points_3d: `(F, P, 3)` camera-frame points (z > 0).
        intrinsics: `(3, 3)` or `(F, 3, 3)` calibration matrices.

    Returns:
        `(F, P, 2)` pixel coordinates.
    """
    k = np.broadcast_to(intrinsics, (points_3d.shape[0], 3, 3))
    h = np.einsum("fij,fpj->fpi", k, points_3d)
    return h[..., :2] / h[..., 2:3]
