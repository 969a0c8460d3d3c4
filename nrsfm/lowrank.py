"""Low-rank fits of `(2F, P)` measurement matrices with missing entries: completion and rank estimation.

Shared by the solvers that complete tracks before factorising them (CSF2, PR, EM-PPCA) and by their automatic K.
A W has frame-pair rows (``2f``, ``2f + 1``: x and y of frame f) and a per-row translation (orthographic
cameras); ``mask`` is True where an entry is visible, and a missing point hides both rows of its frame.
"""

from __future__ import annotations

import numpy as np


def power_of_two_unit(w: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The power of two nearest the RMS of a `(2F, P)` W's visible entries about each row's visible mean (1 when
    that RMS is 0). Dividing by it is exact in floating point and brings any track set to unit order, so a
    solver's absolute constants (damping, tolerances, ridges) mean the same whatever the units of the tracks."""
    mask = np.ones(w.shape, dtype=bool) if mask is None else mask
    count = np.maximum(mask.sum(axis=1, keepdims=True), 1)
    centred = np.where(mask, w - np.where(mask, w, 0.0).sum(axis=1, keepdims=True) / count, 0.0)
    rms = float(np.sqrt((centred**2).sum() / max(int(mask.sum()), 1)))
    return 2.0 ** round(np.log2(rms)) if rms > 0 and np.isfinite(rms) else 1.0


def lowrank_fit(w: np.ndarray, mask: np.ndarray, rank: int, *, start: np.ndarray | None = None,
                rel_tol: float = 1e-6, max_iter: int = 100) -> tuple[float, np.ndarray]:
    """Fit a rank-``rank`` matrix plus a per-row translation to the visible entries of `(2F, P)` ``w``.

    Variable projection (Wiberg; Hong & Fitzgibbon, ICCV 2015): the `(rank, P)` column factor B is optimised by
    Levenberg-Marquardt with Kaufman's Gauss-Newton matrix, the row factors and translations eliminated in closed form
    per frame. ``mask`` rows come in frame pairs (a missing point hides both of its rows). The start is ``start``
    `(r0, P)`, r0 < ``rank`` (a lower-rank fit's factor), completed by the leading directions of the rank-``rank``
    hard imputation (:func:`impute_lowrank`) outside it; or that imputation alone. It has local minima, which fitting
    every rank in turn and random restarts avoid (:func:`visible_rank`).

    The cost depends on the row space of ``[B; 1]`` alone, so the steps move B only along its orthogonal complement
    (``r (P - r - 1)`` unknowns): the Gauss-Newton matrix has no gauge null space, and the minimum reached does not
    depend on rounding.

    Returns:
        The RMS residual on the visible entries over the RMS of the visible entries (each row centred on its visible
        mean), and B `(rank, P)` with orthonormal rows. The search stops once the residual falls below ``rel_tol``,
        when ten iterations gain less than a relative 1e-6, or after ``max_iter`` iterations.
    """
    n_points = w.shape[1]
    ones = np.ones((1, n_points))
    # a frame with at most rank + 1 visible points fits any column factor: it says nothing
    keep = np.repeat(mask[0::2].sum(axis=1) > rank + 1, 2)
    w, mask = w[keep], mask[keep]
    if not len(w):
        return 0.0, np.eye(rank, n_points)
    filled = impute_lowrank(w, mask, rank, iters=10)
    centred = filled - filled.mean(axis=1, keepdims=True)
    if start is None or not len(start):
        b = np.linalg.svd(centred, full_matrices=False)[2][:rank]  # (r, P)
    else:
        known = np.linalg.qr(np.vstack([start, ones]).T)[0]  # (P, r0+1)
        extra = np.linalg.svd(centred - (centred @ known) @ known.T, full_matrices=False)[2][: rank - len(start)]
        b = np.linalg.qr(np.vstack([start, extra]).T)[0].T
    vis = mask[0::2].astype(float)  # (F, P)
    wz = np.where(mask, w, 0.0).reshape(-1, 2, n_points)  # (F, 2, P)
    n_vis = float(mask.sum())
    mean = wz.sum(axis=2, keepdims=True) / np.maximum(vis.sum(axis=1), 1)[:, None, None]
    scale = np.sqrt((((wz - mean) * vis[:, None]) ** 2).sum() / n_vis)
    if scale == 0:
        return 0.0, b

    def evaluate(b: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        bt = np.vstack([b, ones])  # (r+1, P), the last row carries the translation
        bd = bt[None] * vis[:, None]  # (F, r+1, P)
        gram = bd @ bt.T  # (F, r+1, r+1)
        try:
            a = np.linalg.solve(gram, bd @ wz.transpose(0, 2, 1))  # (F, r+1, 2)
        except np.linalg.LinAlgError:  # B's rows and the ones are dependent on some frame's visible points
            return np.inf, None, None, None, None
        e = wz - (a.transpose(0, 2, 1) @ bt) * vis[:, None]  # (F, 2, P)
        return 0.5 * float((e**2).sum()), a, e, bd, gram

    def relative(cost: float) -> float:
        return float(np.sqrt(2 * cost / n_vis) / scale)

    cost, a, e, bd, gram = evaluate(b)
    if not np.isfinite(cost):
        return np.inf, b
    history = [relative(cost)]
    damping = 1e-4
    n_free = n_points - rank - 1  # directions a row of B can move in that change the fit
    for _ in range(max_iter):
        if history[-1] < rel_tol or n_free < 1:
            break
        # the cost depends on the row space of [B; 1] alone: steps along its orthogonal complement Q
        q = np.linalg.qr(np.vstack([b, ones]).T, mode="complete")[0][:, rank + 1:]  # (P, P - r - 1)
        grad, jtj = _gradient_and_gauss_newton(a[:, :rank], e, bd, gram, vis, q)
        diag = np.diag(jtj).copy() + 1e-12 * max(float(np.diag(jtj).max()), 1e-300)
        while damping < 1e10:
            step = np.linalg.solve(jtj + damping * np.diag(diag), -grad.ravel()).reshape(rank, n_free) @ q.T
            trial = evaluate(b + step)
            if trial[0] < cost:
                orthonormal = np.linalg.qr((b + step).T)[0].T  # the same row space, orthonormal rows
                again = evaluate(orthonormal)
                b, (cost, a, e, bd, gram) = (orthonormal, again) if np.isfinite(again[0]) else (b + step, trial)
                damping = max(damping / 10, 1e-12)
                break
            damping *= 10
        history.append(relative(cost))
        if damping >= 1e10 or (len(history) > 10 and history[-11] - history[-1] < 1e-6 * history[-11]):
            break
    return history[-1], b


def _gradient_and_gauss_newton(ar: np.ndarray, e: np.ndarray, bd: np.ndarray, gram: np.ndarray, vis: np.ndarray,
                               q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lowrank_fit`'s gradient `(r, n)` and Kaufman Gauss-Newton matrix `(r n, r n)` in the directions
    ``q`` `(P, n)` (the orthogonal complement of ``[B; 1]``, n = P - r - 1), from the row factors ``ar``
    `(F, r, 2)`, the residuals ``e`` `(F, 2, P)`, the visible rows of ``[B; 1]`` ``bd`` `(F, r+1, P)`, their Gram
    matrices ``gram`` `(F, r+1, r+1)` and the visibility ``vis`` `(F, P)`.

    ``J^T J = sum_f (sum_rows a a^T) kron Q^T (diag(vis_f) - P_f) Q``, ``P_f`` the projection on ``[B; 1]``.
    """
    rank, n_free = ar.shape[1], q.shape[1]
    grad = -np.einsum("fki,fip->kp", ar, e) @ q  # (r, n)
    vq = vis[:, :, None] * q  # (F, P, n)
    c = bd @ vq  # (F, r+1, n)
    proj = q.T @ vq - c.transpose(0, 2, 1) @ np.linalg.solve(gram, c)  # (F, n, n)
    upper = np.triu_indices(rank)  # J^T J's (i, j) and (j, i) blocks are equal: one product for both
    blocks = (ar[:, upper[0]] * ar[:, upper[1]]).sum(axis=2).T @ proj.reshape(len(proj), -1)
    jtj = np.empty((rank, rank, n_free * n_free))
    jtj[upper], jtj[upper[::-1]] = blocks, blocks
    return grad, jtj.reshape(rank, rank, n_free, n_free).transpose(0, 2, 1, 3).reshape(rank * n_free, -1)


def noise_rank(s: np.ndarray, shape: tuple[int, int], *, min_gap: float = 1.5) -> int:
    """The rank of noisy low-rank tracks from the singular values ``s`` of a centred `(2F, P)` W, or 0.

    Gavish & Donoho's hard threshold for white noise of unknown level ("The optimal hard threshold for singular values
    is 4/sqrt(3)", IEEE T-IT 2014): keep the singular values above ``omega(beta) * median(s)``, with
    ``omega(beta) = 0.56 beta^3 - 0.95 beta^2 + 1.82 beta + 1.43`` and ``beta`` the aspect ratio of the `(2F, P - 1)`
    matrix (centring removes one column's worth of rank). The count is returned only where W looks like a low-rank
    signal plus noise:

    * the kept values stand clear of the rest: the last kept at least ``min_gap`` times the first dropped (real motion
      capture decays without such a gap);
    * the median was the noise's: the median of the values beyond the count gives the same count (when the rank is
      more than half of P - 1 the median lies in the signal and the count falls short).

    Args:
        s: singular values of the centred W, descending.
        shape: W's shape `(2F, P)`.
    """
    m, n = shape[0], shape[1] - 1
    size = min(m, n, len(s))
    if size < 2 or s[0] <= 0:
        return 0
    s = np.asarray(s[:size], dtype=np.float64)
    beta = size / max(m, n)
    omega = 0.56 * beta**3 - 0.95 * beta**2 + 1.82 * beta + 1.43
    rank = int(np.count_nonzero(s > omega * np.median(s)))
    if rank < 1 or rank >= size - 1 or s[rank - 1] < min_gap * s[rank]:
        return 0
    if np.count_nonzero(s > omega * np.median(s[rank:])) != rank:
        return 0  # the median was not the noise's: the values beyond the count set another threshold
    return rank


def visible_rank(w: np.ndarray, mask: np.ndarray, max_rank: int, *, rel_tol: float = 1e-6, max_frames: int = 300,
                 max_points: int = 60, restarts: int = 4) -> tuple[int, np.ndarray | None]:
    """The smallest rank r <= ``max_rank`` whose fit (:func:`lowrank_fit`) leaves less than ``rel_tol`` of the RMS of
    the visible entries of `(2F, P)` ``w``, and its column factor over every point.

    Ranks 1, 2, ... are fitted in turn on at most ``max_frames`` evenly spaced frames and ``max_points`` points, each
    started from the fit a rank below (an exactly low-rank W stays so on a subset). Variable projection has local
    minima that this ladder can step over, so from a fitted rank the rank below is tried again from the fill's leading
    directions and from ``restarts`` random starts (fixed seed). First of all one fit at ``max_rank`` (30 iterations)
    screens out tracks that are not low-rank: where it leaves more than 100 ``rel_tol`` the ladder is skipped.

    Returns:
        ``(r, B)`` with B `(r, P)` fitted to every point on the sampled frames (the columns outside the sample by least
        squares on the sampled frames' row factors, then refined), or ``(0, None)`` when no rank up to ``max_rank``
        fits.
    """
    if max_rank < 1:
        return 0, None
    n_points = w.shape[1]
    rows, cols = _rank_sample(mask, max_rank, max_frames, max_points)
    if len(rows) < 4:
        return 0, None
    frames = rows[0::2] // 2
    sub_w, sub_mask = w[np.ix_(rows, cols)], mask[np.ix_(rows, cols)]
    if lowrank_fit(sub_w, sub_mask, max_rank, rel_tol=rel_tol, max_iter=30)[0] > 100 * rel_tol:
        return 0, None  # not even the largest rank comes close: no smaller one fits (real tracks)
    factor, rank = None, 0
    for r in range(1, max_rank + 1):
        residual, factor = lowrank_fit(sub_w, sub_mask, r, start=factor, rel_tol=rel_tol)
        if residual < rel_tol:
            rank = r
            break
    if not rank:
        return 0, None
    rng = np.random.default_rng(0)
    while rank > 1:
        filled = fill_lowrank(sub_w, sub_mask, factor)
        leading = np.linalg.svd(filled - filled.mean(axis=1, keepdims=True), full_matrices=False)[2][: rank - 2]
        starts = [leading] + [np.linalg.qr(rng.standard_normal((len(cols), rank - 2)))[0].T for _ in range(restarts)]
        for start in starts:
            residual, lower = lowrank_fit(sub_w, sub_mask, rank - 1, start=start if len(start) else None,
                                          rel_tol=rel_tol)
            if residual < rel_tol:
                rank, factor = rank - 1, lower
                break
        else:
            break
    if len(cols) < n_points:
        # the sampled frames' row factors and translations, then every point's column by least squares
        w_rows, m_rows = w[rows], mask[rows]
        a = _row_factors(sub_w, sub_mask, factor)  # (F', r+1, 2)
        target = np.where(m_rows, w_rows - a[:, rank].reshape(-1, 1), 0.0)  # (2F', P), less the translations
        try:
            cols_all = masked_lstsq(a[:, :rank].transpose(0, 2, 1), target.reshape(len(frames), 2, n_points),
                                    m_rows[0::2].astype(float), ridge=0.0)  # (r, P)
        except np.linalg.LinAlgError:
            return 0, None
        residual, factor = lowrank_fit(w_rows, m_rows, rank, start=cols_all, rel_tol=rel_tol)
        if residual >= rel_tol:
            return 0, None
    return rank, factor


def _rank_sample(mask: np.ndarray, max_rank: int, max_frames: int, max_points: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The rows (frame pairs) and columns of `(2F, P)` ``mask`` that the rank searches fit: at most ``max_points``
    evenly spaced points, and at most ``max_frames`` evenly spaced frames among those that show more than
    ``max_rank + 1`` of them (fewer say nothing about a rank-``max_rank`` factor)."""
    n_points = mask.shape[1]
    cols = np.unique(np.linspace(0, n_points - 1, min(max_points, n_points)).round().astype(int))
    usable = np.flatnonzero(mask[0::2][:, cols].sum(axis=1) > max_rank + 1)
    frames = usable[np.unique(np.linspace(0, len(usable) - 1, min(max_frames, len(usable))).round().astype(int))]
    return np.stack([2 * frames, 2 * frames + 1], axis=1).ravel(), cols


def noise_visible_rank(w: np.ndarray, mask: np.ndarray, max_rank: int, *, max_frames: int = 300,
                       max_points: int = 60, max_iter: int = 30, restarts: int = 2, min_gap: float = 1.5,
                       max_spread: float = 1.6, min_tail: int = 4) -> int:
    """The rank of noisy low-rank tracks with missing entries (`(2F, P)` ``w``, ``mask`` False where hidden), or 0.

    The counterpart of :func:`noise_rank` where no SVD exists. Ranks 1, ..., ``max_rank`` are fitted to the visible
    entries in turn (:func:`lowrank_fit`, each from the fit a rank below, ``max_iter`` iterations, on the frames and
    points :func:`visible_rank` samples). With complete tracks the residual sum of squares at rank r is the sum of the
    squared singular values beyond r, so ``s_r = sqrt(RSS(r - 1) - RSS(r))`` are the singular values; with missing
    entries they are this ladder's "pseudo singular values". Noisy low-rank tracks show large values up to their rank
    and then a flat floor (the noise's), as a spectrum does:

    * the rank r is the largest with ``s_r >= min_gap * max(s_{r+1}, ...)``, with at least ``min_tail`` values beyond
      it;
    * those values must be flat as noise's are: their spread (largest / smallest) at most ``max_spread`` times that of
      the same values of pure noise, the singular values of a fixed-seed Gaussian matrix of the sampled shape less the
      rank (noise's own spread grows as the matrix gets squarer, Marchenko-Pastur). Real motion capture decays without
      such a floor;
    * the ladder has local minima (a fit at rank r that misses a signal direction and takes a noise one). So the rank
      below is refitted from the fill's leading directions and from ``restarts`` random starts (fixed seed), and the
      rank lowered while that fit leaves the gap below ``min_gap``.
    """
    if max_rank < min_tail + 1:
        return 0
    rows, cols = _rank_sample(mask, max_rank, max_frames, max_points)
    if len(rows) < 4:
        return 0
    sub_w, sub_mask = w[np.ix_(rows, cols)], mask[np.ix_(rows, cols)]
    fits, factors, factor = [1.0], [None], None  # rank 0: the centred RMS, the unit of lowrank_fit's residual
    for r in range(1, max_rank + 1):
        residual, factor = lowrank_fit(sub_w, sub_mask, r, start=factor, rel_tol=0.0, max_iter=max_iter)
        if not np.isfinite(residual):
            return 0
        fits.append(residual)
        factors.append(factor)
    f = np.minimum.accumulate(np.asarray(fits))  # a higher rank fits at least as well
    s = np.sqrt(np.maximum(f[:-1] ** 2 - f[1:] ** 2, 0.0))  # s[r - 1] = s_r
    rank = next((r for r in range(max_rank - min_tail, 0, -1) if s[r - 1] >= min_gap * s[r:].max()), 0)
    if not rank:
        return 0
    floor = s[rank:]
    noise = np.linalg.svd(np.random.default_rng(0).standard_normal((len(rows) - rank, len(cols) - rank)),
                          compute_uv=False)[: len(floor)]  # pure noise's largest singular values, same shape
    if floor.max() * noise[-1] > max_spread * floor.min() * noise[0]:
        return 0  # no flat floor of noise beyond the gap
    rng = np.random.default_rng(0)
    while rank > 1:
        filled = fill_lowrank(sub_w, sub_mask, factors[rank])
        leading = np.linalg.svd(filled - filled.mean(axis=1, keepdims=True), full_matrices=False)[2][: rank - 2]
        starts = [leading] + [np.linalg.qr(rng.standard_normal((len(cols), rank - 2)))[0].T for _ in range(restarts)]
        best = min(lowrank_fit(sub_w, sub_mask, rank - 1, start=st if len(st) else None, rel_tol=0.0,
                               max_iter=max_iter)[0] for st in starts)
        if np.sqrt(max(best**2 - f[rank] ** 2, 0.0)) >= min_gap * floor.max():
            break
        rank -= 1  # the fit at this rank had missed a signal direction: one rank fewer holds the signal
    return rank


def masked_lstsq(a: np.ndarray, b: np.ndarray, vis: np.ndarray, ridge: float = 1e-10) -> np.ndarray:
    """Per column p: argmin_s sum_f vis_fp ||a_f s - b_fp||^2 + ridge' ||s||^2 for `(F, R, C)` a (R rows per
    frame, seen or missing together), `(F, R, P)` b and `(F, P)` visibility, with ``ridge' = ridge * mean diagonal of
    the normal matrix``. The per-point normal matrices come from the per-frame ones (F of them, not F R). Returns
    `(C, P)`.
    """
    n_frames, n_rows, c = a.shape
    if np.all(vis > 0):
        a2 = a.reshape(n_frames * n_rows, c)
        ata = a2.T @ a2
        return np.linalg.solve(ata + ridge * np.trace(ata) / c * np.eye(c), a2.T @ b.reshape(n_frames * n_rows, -1))
    g = a.transpose(0, 2, 1) @ a  # (F, C, C)
    ata = (vis.T @ g.reshape(n_frames, c * c)).reshape(-1, c, c)  # (P, C, C)
    atb = (b * vis[:, None]).reshape(n_frames * n_rows, -1).T @ a.reshape(n_frames * n_rows, c)  # (P, C)
    ridge = ridge * np.trace(ata, axis1=1, axis2=2)[:, None, None] / c * np.eye(c)
    return np.linalg.solve(ata + ridge, atb[..., None])[..., 0].T


def _row_factors(w: np.ndarray, mask: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-frame least-squares coefficients `(F, r+1, 2)` of `(2F, P)` ``w``'s visible entries on `(r, P)` ``b``
    and a translation (the last row); raises ``LinAlgError`` where a frame's visible points cannot fix them."""
    n_frames, n_points = w.shape[0] // 2, w.shape[1]
    bt = np.vstack([b, np.ones((1, n_points))])  # (r+1, P)
    bd = bt[None] * mask[0::2, None].astype(float)  # (F, r+1, P)
    wz = np.where(mask, w, 0.0).reshape(n_frames, 2, n_points)  # (F, 2, P)
    return np.linalg.solve(bd @ bt.T, bd @ wz.transpose(0, 2, 1))


def _lowrank_model(w: np.ndarray, mask: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each frame's least-squares fit `(2F, P)` to the visible entries of `(2F, P)` ``w`` on the `(r, P)` column
    factor ``b`` plus a translation (:func:`_row_factors`)."""
    a = _row_factors(w, mask, b)  # (F, r+1, 2)
    return (a.transpose(0, 2, 1) @ np.vstack([b, np.ones((1, w.shape[1]))])).reshape(w.shape)


def fill_lowrank(w: np.ndarray, mask: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`(2F, P)` ``w`` with its hidden entries (``mask`` False) replaced by each frame's least-squares fit on the
    `(r, P)` column factor ``b`` plus a translation."""
    return np.where(mask, w, _lowrank_model(w, mask, b))


def complete_lowrank(w: np.ndarray, mask: np.ndarray, rank: int, fit: tuple[int, np.ndarray | None] | None = None,
                     *, rel_tol: float = 1e-6) -> tuple[np.ndarray, str]:
    """Complete `(2F, P)` ``w`` at rank ``rank``: exactly when its visible entries are rank <= ``rank`` plus a
    translation per row (:func:`visible_rank`, or ``fit``, its result), otherwise by hard imputation
    (:func:`impute_lowrank`).

    The exact fill uses the smallest such rank (a larger one's completion is not unique) and is kept when it leaves
    less than ``rel_tol`` of the RMS on the visible entries; hard imputation stops short of the exact completion on
    nearly rigid tracks. A point seen in at most r rows does not fix its column, and a frame with at most r + 1
    visible points does not fix its row factor; then the whole W is imputed.

    Returns:
        The filled `(2F, P)` matrix (visible entries unchanged) and ``"exact"`` or ``"imputed"``.
    """
    n_frames, n_points = w.shape[0] // 2, w.shape[1]
    counts = mask[0::2].sum(axis=1)  # (F,)
    found, b = fit if fit is not None else visible_rank(w, mask, rank, rel_tol=rel_tol)
    # every frame must fix its row factor (r + 1 unknowns per row) and every point its column (r unknowns)
    if 0 < found <= rank and counts.min() > found + 1 and mask.sum(axis=0).min() > found:
        try:
            model = _lowrank_model(w, mask, b)  # (2F, P)
        except np.linalg.LinAlgError:
            model = None
        if model is not None:
            wz = np.where(mask, w, 0.0).reshape(n_frames, 2, n_points)  # (F, 2, P)
            centred = (wz - wz.sum(axis=2, keepdims=True) / counts[:, None, None]) * mask[0::2, None]
            if np.linalg.norm(np.where(mask, model - w, 0.0)) < rel_tol * np.linalg.norm(centred):
                return np.where(mask, w, model), "exact"
    return impute_lowrank(w, mask, rank), "imputed"


def impute_lowrank(w: np.ndarray, mask: np.ndarray, rank: int, iters: int = 200, tol: float = 1e-9) -> np.ndarray:
    """Fill the entries of `(2F, P)` ``w`` where ``mask`` is False by iterative rank-``rank`` SVD imputation.

    Rows are centred with the visible entries first (orthographic translation).
    """
    filled = np.where(mask, w, 0.0)
    row_mean = (filled.sum(axis=1) / np.maximum(mask.sum(axis=1), 1))[:, None]
    filled = np.where(mask, w, row_mean)
    for _ in range(iters):
        centred = filled - filled.mean(axis=1, keepdims=True)
        u, s, vt = np.linalg.svd(centred, full_matrices=False)
        approx = (u[:, :rank] * s[:rank]) @ vt[:rank] + filled.mean(axis=1, keepdims=True)
        new = np.where(mask, w, approx)
        change = np.linalg.norm(new - filled) / max(np.linalg.norm(new), 1e-300)
        filled = new
        if change < tol:
            break
    return filled
