"""Orthographic cameras from a rank-3K factorisation: the corrective-matrix (Euclidean) upgrade.

A centred `(2F, P)` W factors as ``M B`` with ``M`` `(2F, 3K)`; the camera rows are ``M Q`` for a `(3K, 3)`
corrective triple ``Q`` that makes every frame's two rows orthonormal. :func:`camera_rows` grows ``Q`` three
columns at a time as Gotardo & Martinez's CSF2 code does (``pgComputeD.m``); :func:`refine_triple` minimises the
scale-invariant residual used by Dai et al.'s SPM refinement. Both minimise with BFGS on the analytic gradient
where the authors call MATLAB's ``fminunc``.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize


def refine_triple(pi: np.ndarray, g0: np.ndarray) -> tuple[np.ndarray, float]:
    """Minimise the scale-invariant orthonormality residual of ``pi @ G`` from ``g0``.

    BFGS (analytic gradient) followed by a Levenberg-Marquardt polish, and LM from ``g0`` alone; the lower cost wins
    (LM alone can stall in a poor minimum).

    Args:
        pi: `(F, 2, 3K)` rank-3K factor; g0: `(3K, 3)` start.

    Returns:
        The refined `(3K, 3)` triple and the final cost (0 for exact data).
    """
    r = pi.shape[2]
    pa, pb = pi[:, 0], pi[:, 1]  # (F, r)

    def residual(g_flat: np.ndarray) -> np.ndarray:
        m = pi @ g_flat.reshape(r, 3)  # (F, 2, 3)
        a, b = m[:, 0], m[:, 1]
        na, nb = (a * a).sum(1), (b * b).sum(1)
        den = na + nb + 1e-300
        return np.concatenate([(na - nb) / den, 2 * (a * b).sum(1) / den])

    def cost_grad(g_flat: np.ndarray) -> tuple[float, np.ndarray]:
        a, b = pa @ g_flat.reshape(r, 3), pb @ g_flat.reshape(r, 3)  # (F, 3)
        na, nb, ab = (a * a).sum(1), (b * b).sum(1), (a * b).sum(1)
        den = na + nb + 1e-300
        e, o = (na - nb) / den, 2 * ab / den
        den2 = den**2
        ca = 2 * (e * 2 * nb - o * 2 * ab) / den2  # d cost / d na, times 2 (d na / d a = 2 a)
        cb = 2 * (-e * 2 * na - o * 2 * ab) / den2
        co = 2 * o / den
        grad = pa.T @ (ca[:, None] * a + co[:, None] * b) + pb.T @ (cb[:, None] * b + co[:, None] * a)
        return 0.5 * float(e @ e + o @ o), grad.ravel()

    # LM needs at least as many residuals (2F) as unknowns (3r); with fewer frames (three frames, K >= 1) the
    # trust-region solver polishes instead
    method = "lm" if 2 * pi.shape[0] >= 3 * r else "trf"

    def polish(g_flat: np.ndarray) -> tuple[np.ndarray, float]:
        res = scipy.optimize.least_squares(residual, g_flat, method=method, max_nfev=2000, xtol=1e-12, ftol=1e-12)
        return res.x, float(res.cost)

    bfgs = scipy.optimize.minimize(cost_grad, g0.ravel(), jac=True, method="BFGS",
                                   options={"gtol": 1e-10, "maxiter": 5000})
    candidates = [polish(bfgs.x), polish(g0.ravel())]
    g, cost = min(candidates, key=lambda c: c[1])
    return g.reshape(r, 3), cost


def camera_rows(wc: np.ndarray, energy: float = 1e-4) -> tuple[np.ndarray, float, int]:
    """Orthographic camera rows from the centred `(2F, P)` W (step 1 of the module docstring).

    Returns:
        `(F, 2, 3)` rows ``M Q`` (nearly orthonormal, not normalised: the shape
        step uses them as they are, like the authors), the final orthonormality
        cost (mean over the 2F rows; 0 for exact data) and the number of columns
        of M used.
    """
    n_frames = wc.shape[0] // 2
    u, s, _ = np.linalg.svd(wc, full_matrices=False)
    n_cols = 3 * int(np.ceil(np.count_nonzero(s / s[0] > energy) / 3))
    if n_cols > u.shape[1]:
        n_cols -= 3
    m = (u[:, :n_cols] * np.sqrt(s[:n_cols])).reshape(n_frames, 2, n_cols)

    def cost_grad(q_flat: np.ndarray, mm: np.ndarray) -> tuple[float, np.ndarray]:
        rows = mm @ q_flat.reshape(-1, 3)  # (F, 2, 3)
        a, b = rows[:, 0], rows[:, 1]
        ea, eb, ab = (a * a).sum(1) - 1, (b * b).sum(1) - 1, (a * b).sum(1)  # (F,)
        scale = 1.0 / n_frames  # the authors' 2 f / (2F)
        # d/dQ of the three residuals: M_f1^T (2 a), M_f2^T (2 b), M_f1^T b + M_f2^T a
        grad = mm[:, 0].T @ (4 * ea[:, None] * a + 2 * ab[:, None] * b) \
            + mm[:, 1].T @ (4 * eb[:, None] * b + 2 * ab[:, None] * a)
        return scale * float(ea @ ea + eb @ eb + ab @ ab), scale * grad.ravel()

    def fit(q0: np.ndarray) -> tuple[np.ndarray, float]:
        res = scipy.optimize.minimize(cost_grad, q0.ravel(), args=(m[:, :, :len(q0)],), jac=True, method="BFGS",
                                      options={"gtol": 1e-12, "maxiter": 2000})
        return res.x.reshape(-1, 3), float(res.fun)

    if n_cols == 3:  # rigid (rank 3): the metric upgrade of the rigid factorisation
        q, best = fit(np.eye(3))
    else:
        q, best = np.eye(3), np.inf
        while q.shape[0] + 3 <= n_cols:  # grow [Q; 0] three columns at a time while the cost falls
            new_q, cost = fit(np.vstack([q, np.zeros((3, 3))]))
            if not cost < best:
                break
            q, best = new_q, cost
    return m[:, :, :q.shape[0]] @ q, best, q.shape[0]
