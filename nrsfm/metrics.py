"""Reconstruction metrics, one function per protocol.

Two families that must never be mixed in one table column:

- *classic NRSfM* (:func:`e3d`, :func:`normalized_error`): shapes in
  arbitrary units, compared after centring;
- *Human3.6M* (:func:`mpjpe_prn`, :func:`pa_mpjpe`, :func:`mpjpe_best_flip`,
  :func:`stress`): millimetres.

Every metric takes its alignment / reflection handling as an explicit
argument, and each has a ``*_per_frame`` variant returning `(F,)` values for
error curves and frame-weighted averages. Shapes are `(F, P, 3)`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from nrsfm.errors import ValidationError, shape_error
from nrsfm.geometry import nearest_rotation

Frame = Literal["camera", "object"]


def _check_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if gt.ndim != 3 or gt.shape[-1] != 3:
        raise shape_error("gt", "(F, P, 3)", gt.shape)
    if pred.shape != gt.shape:
        raise shape_error("pred", f"the ground truth's shape {gt.shape}", pred.shape)
    if not (np.isfinite(pred).all() and np.isfinite(gt).all()):
        raise ValidationError("pred/gt: expected finite values, got NaN or inf")
    return pred, gt


def _centre(x: np.ndarray) -> np.ndarray:
    return x - x.mean(axis=1, keepdims=True)


def _flip_z(x: np.ndarray) -> np.ndarray:
    return x * np.array([1.0, 1.0, -1.0])


# --------------------------------------------------------------------------- e3D
def e3d_per_frame(pred: np.ndarray, gt: np.ndarray, *, frame: Frame = "camera",
                  pred_rotations: np.ndarray | None = None, gt_rotations: np.ndarray | None = None,
                  allow_reflection: bool = True) -> np.ndarray:
    """Per-frame e3D of the classic NRSfM tables (Akhter et al.); see :func:`e3d`.

    Returns:
        `(F,)` mean per-point error of each frame divided by the sequence scale.
    """
    pred, gt = _check_pair(pred, gt)
    pred, gt = _centre(pred), _centre(gt)
    if frame == "object":
        if pred_rotations is None or gt_rotations is None:
            raise ValidationError("e3d(frame='object'): expected pred_rotations and gt_rotations (F, 3, 3), got "
                                  "None; object-frame e3D needs the cameras of both (use frame='camera' otherwise)")
        n = gt.shape[0]
        for nm, r in (("pred_rotations", pred_rotations), ("gt_rotations", gt_rotations)):
            if np.shape(r) != (n, 3, 3):
                raise shape_error(nm, f"(F, 3, 3) with F = {n}", np.shape(r))
        # X_obj = R^T X_cam, with points as rows: x_obj = x_cam @ R
        pred = np.einsum("fpi,fij->fpj", pred, np.asarray(pred_rotations, dtype=np.float64))
        gt = np.einsum("fpi,fij->fpj", gt, np.asarray(gt_rotations, dtype=np.float64))
    elif frame != "camera":
        raise ValidationError(f"frame: expected 'camera' or 'object', got {frame!r}")
    a = pred.reshape(-1, 3)  # (F*P, 3)
    b = gt.reshape(-1, 3)
    # one global 3x3 least-squares fit b ~ a Q^T, projected to the nearest orthogonal matrix
    q_ls = np.linalg.lstsq(a, b, rcond=None)[0].T  # (3, 3)
    q = nearest_rotation(q_ls, allow_reflection=allow_reflection)
    aligned = pred @ q.T
    # scale: mean over the 3F rows of the ground truth (3F x P) of each row's std over points
    scale = gt.std(axis=1).mean()
    if scale <= 0:
        raise ValidationError("gt: expected a non-degenerate ground truth, got zero spread")
    return np.linalg.norm(aligned - gt, axis=2).mean(axis=1) / scale


def e3d(pred: np.ndarray, gt: np.ndarray, *, frame: Frame = "camera", pred_rotations: np.ndarray | None = None,
        gt_rotations: np.ndarray | None = None, allow_reflection: bool = True) -> float:
    """e3D: relative 3D error of the classic NRSfM benchmark.

    Protocol: shapes are centred per frame; with ``frame='object'`` both are
    first taken to their object frames (``R^T X``, each with its own per-frame
    rotations); one global 3x3 least-squares fit of the prediction to the
    ground truth over the whole sequence is projected to the nearest
    orthogonal matrix (a reflection when ``allow_reflection``, the default, as
    the depth sign of orthographic NRSfM is ambiguous); the per-point
    Euclidean error is divided by ``s`` = mean over the 3F rows of the ground
    truth's `(3F, P)` matrix of the row's standard deviation over points
    (population std); the mean over points and frames is returned.

    Args:
        pred, gt: `(F, P, 3)` shapes in the camera frame.
        frame: ``'camera'`` (default) or ``'object'`` (needs both rotations).
        pred_rotations, gt_rotations: `(F, 3, 3)` camera rotations, ``X_cam = R X_obj``.
    """
    return float(e3d_per_frame(pred, gt, frame=frame, pred_rotations=pred_rotations, gt_rotations=gt_rotations,
                               allow_reflection=allow_reflection).mean())


# --------------------------------------------------------------------------- cameras
def rotation_error_per_frame(pred_rotations: np.ndarray, gt_rotations: np.ndarray) -> np.ndarray:
    """Per-frame camera error of Akhter et al. (NIPS 2008), the ``Rotation_Err`` of Dai et al.'s SPM code.

    The two camera rows of every frame are stacked into `(2F, 3)` matrices; one global orthogonal matrix (least
    squares, a reflection allowed: the depth sign of orthographic NRSfM is ambiguous) takes the prediction's rows to
    the ground truth's; each frame's error is the spectral norm (the largest singular value) of its `(2, 3)`
    difference, as ``norm()`` of a matrix in their MATLAB code (``compareRotations``). 0 for exact cameras;
    ``2 sin(t / 2)`` for a frame turned by ``t`` about the optical axis (2 at 180 degrees).

    Args:
        pred_rotations, gt_rotations: `(F, 3, 3)` camera rotations, ``X_cam = R X_obj`` (rows: the camera axes).

    Returns:
        `(F,)` per-frame errors.
    """
    pred = np.asarray(pred_rotations, dtype=np.float64)
    gt = np.asarray(gt_rotations, dtype=np.float64)
    if pred.ndim != 3 or pred.shape[1:] != (3, 3):
        raise shape_error("pred_rotations", "(F, 3, 3)", pred.shape)
    if gt.shape != pred.shape:
        raise shape_error("gt_rotations", f"(F, 3, 3) with F = {pred.shape[0]} like pred_rotations", gt.shape)
    a, b = pred[:, :2].reshape(-1, 3), gt[:, :2].reshape(-1, 3)
    residual = a @ nearest_rotation(a.T @ b, allow_reflection=True) - b  # (2F, 3)
    return np.linalg.norm(residual.reshape(-1, 2, 3), ord=2, axis=(1, 2))


def camera_moves(rotations: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether `(F, 3, 3)` camera ``rotations`` differ between frames. Against a static ground-truth camera
    (CMU dance: no ``Rs`` in the file, the rows fitted to its ``S`` are one camera) the object frame and the
    camera error carry no information about a solver's per-frame rotations."""
    return bool(np.ptp(np.asarray(rotations, dtype=np.float64), axis=0).max() > tol)


def rotation_error(pred_rotations: np.ndarray, gt_rotations: np.ndarray) -> float:
    """Mean of :func:`rotation_error_per_frame`."""
    return float(rotation_error_per_frame(pred_rotations, gt_rotations).mean())


# ------------------------------------------------------------------ normalised error
def normalized_error_per_frame(pred: np.ndarray, gt: np.ndarray, *, z_sign: Literal["per_frame", "none"] = "per_frame"
                               ) -> np.ndarray:
    """Per-frame ``||X - X^||_F / ||X||_F`` on centred shapes; see :func:`normalized_error`."""
    pred, gt = _check_pair(pred, gt)
    pred, gt = _centre(pred), _centre(gt)
    denom = np.linalg.norm(gt.reshape(gt.shape[0], -1), axis=1)
    denom = np.where(denom > 0, denom, 1.0)
    err = np.linalg.norm((pred - gt).reshape(gt.shape[0], -1), axis=1)
    if z_sign == "per_frame":
        err = np.minimum(err, np.linalg.norm((_flip_z(pred) - gt).reshape(gt.shape[0], -1), axis=1))
    elif z_sign != "none":
        raise ValidationError(f"z_sign: expected 'per_frame' or 'none', got {z_sign!r}")
    return err / denom


def normalized_error(pred: np.ndarray, gt: np.ndarray, *, z_sign: Literal["per_frame", "none"] = "per_frame"
                     ) -> float:
    """Normalised 3D error (Lee et al.; PRN Tables 3-4).

    Protocol: both shapes centred per frame, no rotation alignment (camera
    frame); per frame ``||X - X^||_F / ||X||_F`` with the sign of z chosen per
    frame (the smaller error) when ``z_sign='per_frame'``; mean over frames.
    """
    return float(normalized_error_per_frame(pred, gt, z_sign=z_sign).mean())


# --------------------------------------------------------------------------- MPJPE
def mpjpe_prn_per_frame(pred: np.ndarray, gt: np.ndarray, *, z_sign: Literal["per_frame", "none"] = "per_frame"
                        ) -> np.ndarray:
    """Per-frame MPJPE under PRN's Human3.6M protocol; see :func:`mpjpe_prn`."""
    return mpjpe_prn_per_joint(pred, gt, z_sign=z_sign).mean(axis=1)


def prn_frames(pred: np.ndarray, gt: np.ndarray, *, z_sign: Literal["per_frame", "none"] = "per_frame"
               ) -> tuple[np.ndarray, np.ndarray]:
    """`(F, P, 3)` predictions and ground truth as PRN's Human3.6M protocol (:func:`mpjpe_prn`) compares them:
    each frame centred on all its joints, the prediction's z sign chosen per frame on all of them."""
    pred, gt = _check_pair(pred, gt)
    pred, gt = _centre(pred), _centre(gt)
    if z_sign == "per_frame":
        flat = lambda x: x.reshape(x.shape[0], -1)  # noqa: E731
        keep = np.linalg.norm(flat(pred - gt), axis=1) <= np.linalg.norm(flat(_flip_z(pred) - gt), axis=1)
        pred = np.where(keep[:, None, None], pred, _flip_z(pred))
    elif z_sign != "none":
        raise ValidationError(f"z_sign: expected 'per_frame' or 'none', got {z_sign!r}")
    return pred, gt


def mpjpe_prn_per_joint(pred: np.ndarray, gt: np.ndarray, *, z_sign: Literal["per_frame", "none"] = "per_frame"
                        ) -> np.ndarray:
    """`(F, P)` joint errors (mm) under PRN's Human3.6M protocol (:func:`mpjpe_prn`): each frame centred on all its
    joints and its z sign chosen on all of them (:func:`prn_frames`), so a subset's mean error (e.g. the joints
    missing from the input) is measured in the frame the full MPJPE uses."""
    pred, gt = prn_frames(pred, gt, z_sign=z_sign)
    return np.linalg.norm(pred - gt, axis=2)


def mpjpe_prn(pred: np.ndarray, gt: np.ndarray, *, z_sign: Literal["per_frame", "none"] = "per_frame") -> float:
    """MPJPE (mm) under PRN's Human3.6M protocol (official ``testH36M_*.m``).

    Protocol: ``pred`` and ``gt`` in millimetres (a network trained on
    normalised inputs is scaled back by the ground truth's xy Frobenius norm
    before calling this); both centred on the mean of the joints (not the
    root); the z sign chosen per frame by the normalised error when
    ``z_sign='per_frame'``; no Procrustes alignment; mean joint error over
    frames (frame-weighted).
    """
    return float(mpjpe_prn_per_frame(pred, gt, z_sign=z_sign).mean())


def pa_mpjpe_per_frame(pred: np.ndarray, gt: np.ndarray, *, allow_reflection: bool = False) -> np.ndarray:
    """Per-frame MPJPE after a per-frame similarity (Procrustes) alignment; see :func:`pa_mpjpe`."""
    pred, gt = _check_pair(pred, gt)
    pred, gt = _centre(pred), _centre(gt)
    h = np.einsum("fpi,fpj->fij", pred, gt)  # (F, 3, 3)
    rot = nearest_rotation(h, allow_reflection=allow_reflection)  # pred @ rot ~ gt
    norm = (pred**2).sum(axis=(1, 2))
    scale = np.einsum("fij,fij->f", rot, h) / np.where(norm > 0, norm, 1.0)  # tr(R^T H): the signed singular values
    aligned = scale[:, None, None] * pred @ rot
    return np.linalg.norm(aligned - gt, axis=2).mean(axis=1)


def pa_mpjpe(pred: np.ndarray, gt: np.ndarray, *, allow_reflection: bool = False) -> float:
    """PA-MPJPE (mm): per frame, centre, then the best rotation and scale (Procrustes) before MPJPE.

    ``allow_reflection=False`` (default, as VideoPose3D) keeps det(R) = +1.
    """
    return float(pa_mpjpe_per_frame(pred, gt, allow_reflection=allow_reflection).mean())


def mpjpe_best_flip_per_frame(pred: np.ndarray, gt: np.ndarray, *, root: int | None = 0) -> np.ndarray:
    """Per-frame C3DPO MPJPE; see :func:`mpjpe_best_flip`."""
    pred, gt = _check_pair(pred, gt)
    if root is None:
        pred, gt = _centre(pred), _centre(gt)
    else:
        pred = pred - pred[:, root:root + 1]
        gt = gt - gt[:, root:root + 1]
    raw = np.linalg.norm(pred - gt, axis=2).mean(axis=1)
    flipped = np.linalg.norm(_flip_z(pred) - gt, axis=2).mean(axis=1)
    return np.minimum(raw, flipped)


def mpjpe_best_flip(pred: np.ndarray, gt: np.ndarray, *, root: int | None = 0) -> float:
    """C3DPO's MPJPE: centred on the ``root`` joint (hip; ``None`` = the mean), the better of the
    raw and the depth-flipped prediction per sample, no rotation alignment."""
    return float(mpjpe_best_flip_per_frame(pred, gt, root=root).mean())


def stress_per_frame(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame stress; see :func:`stress`."""
    pred, gt = _check_pair(pred, gt)
    dp = np.linalg.norm(pred[:, :, None] - pred[:, None], axis=-1)  # (F, P, P)
    dg = np.linalg.norm(gt[:, :, None] - gt[:, None], axis=-1)
    p = gt.shape[1]
    iu = np.triu_indices(p, k=1)
    return np.abs(dp - dg)[:, iu[0], iu[1]].mean(axis=1)


def stress(pred: np.ndarray, gt: np.ndarray) -> float:
    """C3DPO's stress: mean absolute difference of the pairwise distance matrices (over point
    pairs i < j), averaged over frames. Invariant to rotation, translation and reflection."""
    return float(stress_per_frame(pred, gt).mean())


def classic_metrics(pred: np.ndarray, gt: np.ndarray, *, pred_rotations: np.ndarray | None = None,
                    gt_rotations: np.ndarray | None = None) -> dict[str, float]:
    """The numbers ``nrsfm solve`` prints: e3D (camera frame, and object frame and the camera error of
    :func:`rotation_error` when both rotations are known and the ground-truth camera moves), normalised error
    and MPJPE (PRN protocol, in the data's units)."""
    out = {
        "e3d": e3d(pred, gt),
        "normalized_error": normalized_error(pred, gt),
        "mpjpe": mpjpe_prn(pred, gt),
    }
    if pred_rotations is not None and gt_rotations is not None and camera_moves(gt_rotations):
        out["e3d_object"] = e3d(pred, gt, frame="object", pred_rotations=pred_rotations, gt_rotations=gt_rotations)
        out["rotation_error"] = rotation_error(pred_rotations, gt_rotations)
    return out
