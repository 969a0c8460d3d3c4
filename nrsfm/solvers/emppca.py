"""EM-PPCA: NRSfM with a Gaussian (probabilistic PCA) shape model fitted by EM (Torresani, Hertzmann & Bregler,
PAMI 2008), with an optional first-order Procrustean constraint on the modes.

Model (orthographic): each frame's shape is a sample of a Gaussian around the mean shape, seen by a rotated
camera::

    w_fp = R_f^(2) (m_p + sum_k z_fk v_kp) + t_f + noise,   z_f ~ N(0, I_K),  noise ~ N(0, s2 I)

The *Procrustean* option (``procrustean=True``) keeps the deformation modes ``v_k`` `(3, P)` orthogonal to the
infinitesimal rotations ``[e_i]_x M`` and translations of the mean shape ``M``, so rigid motion is explained by
the cameras alone (a first-order form of the PND alignment constraint; the full PND model is
:mod:`nrsfm.solvers.empnd`). Without it (the default) the model is Torresani et al.'s.

EM: the E-step gives each frame's Gaussian posterior over ``z_f`` from its visible entries (missing points are
simply absent from the likelihood); the M-step updates, in closed form per point, the mean shape and modes, the
noise variance and translations, and each camera's rows by a few majorisation steps of the quadratic expected cost
on the Stiefel manifold (``R <- polar(B + R (L I - C))``). All of it is batched matrix products.

Initialisation (``init``): ``"csf2"`` (default) takes the cameras from CSF2 and the mean and modes from a PCA of
CSF2's object-frame shapes (Torresani et al. start from a rigid fit, whose cameras can be far off on real motion);
the rigid rank-3 factorisation (``"rigid"``) is the fallback for tiny sequences.

K, unless given: ``DEFAULT_K`` (at most a quarter of the frames), except where the centred tracks have an exact rank
r (noise-free; :func:`~nrsfm.solvers.starts.exact_rank`: one SVD, or with missing points a ladder of rank fits,
about a second on the CMU files) at least a rank-3 basis below its largest, P - 1. (A smaller deficiency comes from
points that depend on others, not from a shape model: Human3.6M's 17 joints, the pelvis midway between the hips,
have rank 15.) The shapes then span the K' = :func:`~nrsfm.solvers.starts.k_for_rank` rank-3 bases that CSF2's rank
rule gives r, and the model's mean and K modes span K + 1: K = K' - 1 is kept where its fit is exact (noise
deviation at most ``EXACT_FIT`` of the tracks' RMS: the mean is one of the bases), else K = K' (shapes whose span
does not hold their mean).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nrsfm.errors import ValidationError
from nrsfm.geometry import complete_rotation, nearest_rotation
from nrsfm.progress import report
from nrsfm.sequence import Sequence
from nrsfm.lowrank import impute_lowrank, power_of_two_unit
from nrsfm.reconstruction import Reconstruction
from nrsfm.solvers.rank3 import Rank3Params, solve_rank3
from nrsfm.solvers.registry import register, require_visible_points
from nrsfm.solvers.starts import csf2_reconstruction, exact_rank, k_for_rank, shared_starts


#: K when not given and the tracks are not exactly low-rank: the Gaussian prior on the coefficients keeps unused
#: modes small, so a generous K is safe (chosen on the CMU files among 5, 10 and 15).
DEFAULT_K = 10
#: Where the tracks are exactly low-rank: a fit is exact when its noise deviation is at most this fraction of the
#: RMS of the centred visible tracks.
EXACT_FIT = 1e-4


@dataclass(frozen=True)
class EMPPCAParams:
    """Parameters of :func:`solve_emppca` (``K = 0``: automatic).

    Attributes:
        max_iter: EM iterations; tol: stop when the relative change of the expected reconstruction between
            iterations falls below it.
        rotation_steps: majorisation steps of the camera update per iteration.
        seed: initialisation of the deformation modes.
        init: ``"csf2"`` or ``"rigid"`` start; init_K: CSF2's K for the start (0: CSF2's rank rule).
        procrustean: project the modes off the rotations/translations of the mean after every M-step (the
            first-order PND constraint). Off by default: on exact low-rank data the projection biases the fit.
    """

    K: int = 0
    max_iter: int = 300
    tol: float = 1e-7
    rotation_steps: int = 5
    seed: int = 0
    procrustean: bool = False
    init: str = "csf2"
    init_K: int = 0

    def __post_init__(self) -> None:
        if self.init not in ("csf2", "rigid"):
            raise ValidationError(f"init: expected 'csf2' or 'rigid', got {self.init!r}")
        if self.K < 0 or self.max_iter < 1 or self.rotation_steps < 1:
            raise ValidationError(f"EMPPCAParams: expected K >= 0, max_iter >= 1, rotation_steps >= 1, got "
                                  f"{self.K}, {self.max_iter}, {self.rotation_steps}")


def _procrustean_projection(modes: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Remove from `(K, 3, P)` modes their components along rotations and translations of `(3, P)` ``mean``."""
    n_points = mean.shape[1]
    dirs = []
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        dirs.append(np.cross(e[:, None], mean, axis=0).ravel())  # [e_i]_x M
        t = np.zeros((3, n_points))
        t[i] = 1.0
        dirs.append(t.ravel())
    basis, _ = np.linalg.qr(np.stack(dirs, axis=1))  # (3P, 6)
    flat = modes.reshape(len(modes), -1)
    return (flat - (flat @ basis) @ basis.T).reshape(modes.shape)


@register("emppca", EMPPCAParams, "EM-PPCA: Gaussian low-rank shape model fitted by EM (Torresani et al., PAMI 2008)",
          handles_missing=True)
def solve_emppca(seq: Sequence, params: EMPPCAParams) -> Reconstruction:
    """EM-PPCA on an orthographic sequence (missing points allowed). See the module docstring."""
    require_visible_points(seq, "emppca")
    if params.K:
        return _em(seq, params, params.K)
    vis = np.repeat(seq.weights > 0, 2, axis=0)  # (2F, P)
    wm = seq.measurement_matrix()
    with shared_starts():  # the rank of tracks with missing points and CSF2's start, once for CSF2 and both Ks
        rank = exact_rank(wm / power_of_two_unit(wm, vis), vis)  # in CSF2's units: its own rank, shared
        if not rank or rank > seq.n_points - 4:  # a deficiency smaller than a basis: points that depend on others
            return _em(seq, params, min(DEFAULT_K, max(1, seq.n_frames // 4)))
        bases = k_for_rank(rank, rank)
        if bases > 1:
            rec = _em(seq, params, bases - 1)
            if rec.info["noise_std"] <= EXACT_FIT * _centred_rms(wm, vis):
                return rec
        return _em(seq, params, bases)


def _centred_rms(w: np.ndarray, vis: np.ndarray) -> float:
    """The RMS of the visible entries of `(2F, P)` ``w`` (``vis`` True) about their row's mean."""
    seen = np.where(vis, w, 0.0)
    counts = np.maximum(vis.sum(axis=1, keepdims=True), 1)
    return float(np.sqrt((np.where(vis, seen - seen.sum(axis=1, keepdims=True) / counts, 0.0)**2).sum() / vis.sum()))


def _em(seq: Sequence, params: EMPPCAParams, k: int) -> Reconstruction:
    """EM-PPCA with ``k`` modes (at most P - 2): the start and the EM iterations."""
    n_frames, n_points = seq.n_frames, seq.n_points
    vis = (seq.weights > 0).astype(np.float64)  # (F, P)
    w = seq.points_2d.copy()  # (F, P, 2)
    wm = seq.measurement_matrix()
    filled = impute_lowrank(wm, np.repeat(vis > 0, 2, axis=0), 9) if vis.min() == 0 else wm
    k = max(1, min(k, (3 * n_points - 6) // 3))
    fp2 = filled.reshape(n_frames, 2, n_points).transpose(0, 2, 1)  # (F, P, 2)
    t = fp2.mean(axis=1)  # (F, 2)
    w = np.where(vis[..., None] > 0, w, fp2)
    init, r2, mean, modes = _start(seq, fp2, k, params)
    scale = np.sqrt((mean**2).sum() / n_points)
    if params.procrustean:
        modes = _procrustean_projection(modes, mean)
    resid0 = w - t[:, None] - np.einsum("fij,jp->fpi", r2, mean)
    s2 = max((resid0**2 * vis[..., None]).sum() / (2 * vis.sum()), 1e-12 * scale**2)
    prev = None
    it = 0
    converged = False
    eye_k = np.eye(k)
    vis_sum = vis.sum()
    w_fip = w.transpose(0, 2, 1)  # (F, 2, P)
    vis_f1p = vis[:, None, :]
    for it in range(1, params.max_iter + 1):
        # ---- E-step: posterior of z_f (K) from the visible entries (everything as batched matmuls)
        a = (r2 @ modes.transpose(1, 0, 2).reshape(3, k * n_points)).reshape(n_frames, 2, k, n_points)
        a = a.transpose(0, 2, 1, 3).reshape(n_frames, k, 2 * n_points)  # (F, K, 2P): rows R_f^(2) v_k
        wt = (w_fip - t[:, :, None]) * vis_f1p  # (F, 2, P) centred visible observations
        r = (wt - (r2 @ mean) * vis_f1p).reshape(n_frames, 2 * n_points)  # (F, 2P) residual of the mean
        av = a * np.tile(vis, 2)[:, None, :]  # (F, K, 2P)
        ata = av @ a.transpose(0, 2, 1)  # (F, K, K)
        cov = np.linalg.inv(eye_k + ata / s2)  # (F, K, K)
        mu = (cov @ (av @ r[..., None]))[..., 0] / s2  # (F, K)
        # ---- M-step: mean and modes per point
        mean, modes = _shape_model_step(vis, r2, wt, mu, cov)
        if params.procrustean:
            modes = _procrustean_projection(modes, mean)
        # ---- cameras: minimise tr(R C R^T) - 2 tr(R B^T) over orthonormal rows
        es = mean[None] + (mu @ modes.reshape(k, 3 * n_points)).reshape(n_frames, 3, n_points)  # (F, 3, P) E[s_fp]
        # E[s s^T] per frame, summed over visible points: E[s]E[s]^T + sum_kl cov_kl v_k v_l^T
        esv = es * vis_f1p
        outer = (modes[:, :, None, None, :] * modes[None, None, :, :, :]).transpose(4, 0, 1, 2, 3)  # (P, K, 3, K, 3)
        spread = (vis @ outer.reshape(n_points, -1)).reshape(n_frames, k, 3, k, 3)
        t_mat = np.einsum("fkjli,fkl->fji", spread, cov)  # (F, 3, 3)
        c_mat = esv @ es.transpose(0, 2, 1) + t_mat
        b_mat = wt @ es.transpose(0, 2, 1)  # (F, 2, 3)
        lmax = np.linalg.eigvalsh(c_mat)[:, -1]  # (F,)
        for _ in range(params.rotation_steps):
            r2 = nearest_rotation(b_mat + r2 @ (lmax[:, None, None] * np.eye(3) - c_mat), allow_reflection=True)
        # ---- translations and noise
        proj = r2 @ es  # (F, 2, P)
        t = ((w_fip - proj) * vis_f1p).sum(axis=2) / vis.sum(axis=1)[:, None]
        res = (w_fip - t[:, :, None] - proj) * vis_f1p
        extra = np.einsum("fij,fjk,fik->", r2, t_mat, r2)
        s2 = max(((res**2).sum() + extra) / (2 * vis_sum), 1e-14 * scale**2)
        recon = complete_rotation(r2) @ es
        report("emppca", "EM", it, params.max_iter, noise_std=np.sqrt(s2) / scale)
        if prev is not None:
            change = np.linalg.norm(recon - prev) / max(np.linalg.norm(recon), 1e-300)
            if change < params.tol:
                converged = True
                break
        prev = recon
    rot = complete_rotation(r2)
    points = (rot @ es).transpose(0, 2, 1)
    points -= points.mean(axis=1, keepdims=True)
    return Reconstruction(points_3d=points, rotations=rot, method="emppca", iterations=it, converged=converged,
                          info={"K": k, "noise_std": float(np.sqrt(s2)), "init": init})


def _start(seq: Sequence, fp2: np.ndarray, k: int, params: EMPPCAParams):
    """The start (module docstring, "Initialisation") for `(F, P, 2)` completed tracks ``fp2``: the start used,
    camera rows `(F, 2, 3)`, the mean shape `(3, P)` and ``k`` modes `(K, 3, P)`, all in the object frame."""
    n_frames, n_points = seq.n_frames, seq.n_points
    rng = np.random.default_rng(params.seed)
    init = params.init
    if init == "csf2" and min(2 * n_frames, n_points) < 6:
        init = "rigid"  # CSF2 needs 3K <= min(2F, P) with K >= 2; tiny sequences start rigid (documented fallback)
    if init == "csf2":  # cameras, mean and modes from CSF2's reconstruction (PCA of its object-frame shapes)
        k_init = min(params.init_K, min(2 * n_frames, n_points) // 3)  # 0: CSF2's rank rule
        start = csf2_reconstruction(seq, k_init)
        r2 = start.rotations[:, :2].copy()
        obj = start.shapes_object.transpose(0, 2, 1)  # (F, 3, P)
        mean = obj.mean(axis=0)
        _, sv, vt = np.linalg.svd((obj - mean).reshape(n_frames, -1), full_matrices=False)
        modes = (sv[:k, None] / np.sqrt(n_frames) * vt[:k]).reshape(k, 3, n_points)
        modes += 1e-3 * np.sqrt((mean**2).sum() / n_points) * rng.standard_normal(modes.shape)  # none exactly 0
    else:  # the rigid rank-3 factorisation
        rigid = solve_rank3.__wrapped__(Sequence(points_2d=fp2), Rank3Params())
        r2 = rigid.rotations[:, :2].copy()  # (F, 2, 3)
        mean = np.einsum("fpi,fij->jp", rigid.points_3d, rigid.rotations) / n_frames  # (3, P) object frame
        modes = 0.1 * np.sqrt((mean**2).sum() / n_points) * rng.standard_normal((k, 3, n_points))
    return init, r2, mean, modes


def _shape_model_step(vis: np.ndarray, r2: np.ndarray, wt: np.ndarray, mu: np.ndarray, cov: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The M-step of the mean shape and the modes: per point p, ``theta_p = [m_p; v_1p; ...; v_Kp]`` `(3(K+1))` by
    least squares on the expected statistics. ``vis`` `(F, P)`, camera rows ``r2`` `(F, 2, 3)`, centred visible
    observations ``wt`` `(F, 2, P)`, posterior means ``mu`` `(F, K)` and covariances ``cov`` `(F, K, K)`.
    Returns the mean `(3, P)` and the modes `(K, 3, P)`."""
    n_frames, k = mu.shape
    n_points = vis.shape[1]
    kk = 3 * (k + 1)
    zh = np.concatenate([np.ones((n_frames, 1)), mu], axis=1)  # (F, K+1)
    ezh = np.empty((n_frames, k + 1, k + 1))
    ezh[:, 0, 0] = 1.0
    ezh[:, 0, 1:] = ezh[:, 1:, 0] = mu
    ezh[:, 1:, 1:] = cov + mu[:, :, None] * mu[:, None, :]  # E[z z^T]
    rtr = r2.transpose(0, 2, 1) @ r2  # (F, 3, 3)
    kron = (ezh[:, :, None, :, None] * rtr[:, None, :, None, :]).reshape(n_frames, kk * kk)
    lhs = (vis.T @ kron).reshape(n_points, kk, kk)  # sum_f vis_fp Ezh_f kron R_f^T R_f
    g = r2.transpose(0, 2, 1) @ wt  # (F, 3, P)
    rhs = (zh.T @ g.reshape(n_frames, 3 * n_points)).reshape(k + 1, 3, n_points).transpose(2, 0, 1)
    ridge = 1e-9 * np.trace(lhs, axis1=1, axis2=2)[:, None, None] / kk * np.eye(kk)
    theta = np.linalg.solve(lhs + ridge, rhs.reshape(n_points, kk, 1))[..., 0].reshape(n_points, k + 1, 3)
    return theta[:, 0].T, theta[:, 1:].transpose(1, 2, 0)
