"""The one data contract: :class:`Sequence`.

A sequence is a set of 2D observations of the same `P` points over `F`
frames, frame-major with coordinates last::

    points_2d   (F, P, 2)  observed image coordinates
    visibility  (F, P)     in [0, 1]; 0 = missing, fractional = confidence
    points_3d   (F, P, 3)  optional ground truth in the *camera* frame

For orthographic data the orthographic projection of ``points_3d`` (its first
two coordinates) is ``points_2d``; for perspective data ``points_2d`` are
pixels and ``intrinsics`` holds the calibration.

Classic layouts (the 2F x P interleaved measurement matrix, the 3 x P x F
PND array) are reached only through the converters in
:mod:`nrsfm.converters`.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nrsfm.errors import DataFormatError, ValidationError, shape_error
from nrsfm.io import atomic_write, is_reconstruction, read_npz

PROJECTIONS = ("orthographic", "perspective")
FORMAT_VERSION = 1


def as_float_array(name: str, value: Any) -> np.ndarray:
    """``value`` as a float64 array; a :class:`ValidationError` naming ``name`` for text, objects or complex
    numbers (numpy would drop an imaginary part with only a warning)."""
    if np.iscomplexobj(value):
        raise ValidationError(f"{name}: expected real numbers, got complex values; pass the real part "
                              "(np.real) if the imaginary part is rounding noise")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValidationError(f"{name}: expected a numeric array, got {type(value).__name__} ({exc})") from None
    return arr


def _freeze(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    arr.setflags(write=False)
    return arr


def _layout_hint(shape: tuple[int, ...]) -> str:
    if len(shape) == 2 and shape[0] % 2 == 0:
        return "looks like the 2F x P measurement matrix, use nrsfm.converters.from_measurement_matrix()"
    if len(shape) == 3 and shape[0] in (2, 3) and shape[2] not in (2, 3):
        return "looks like the 3 x P x F (PND) layout, use nrsfm.converters.from_pnd()"
    if len(shape) == 3 and shape[1] == 2:
        return "looks like a channel-first (F, 2, P) array, transpose it with .transpose(0, 2, 1)"
    return "arrays are frame-major with coordinates last"


@dataclass(frozen=True, eq=False)
class Sequence:
    """2D tracks of `P` points over `F` frames, with optional ground truth.

    Attributes:
        points_2d: `(F, P, 2)` image coordinates (orthographic units or pixels).
            Entries whose visibility is 0 are ignored; NaN is allowed there and
            is replaced by 0 at construction.
        visibility: `(F, P)` weights in [0, 1], 0 = missing. ``None`` means
            every point is visible with weight 1.
        points_3d: `(F, P, 3)` ground-truth shapes in the camera frame, or
            ``None``.
        projection: ``"orthographic"`` or ``"perspective"``.
        intrinsics: `(3, 3)` or `(F, 3, 3)` calibration for perspective data.
        camera_rotations: `(F, 3, 3)` ground-truth rotations from the object
            (world) frame to the camera frame, ``points_3d[f].T = R[f] @
            S_world[f]`` up to translation; used by the object-frame e3D.
        name: free-form identifier (also seeds per-sequence randomness).
        joint_names: `P` names, or ``None``.
        edges: `(E, 2)` 0-based point index pairs for drawing, or ``None``.
        fps: frame rate in Hz, or ``None``.
    """

    points_2d: np.ndarray
    visibility: np.ndarray | None = None
    points_3d: np.ndarray | None = None
    projection: str = "orthographic"
    intrinsics: np.ndarray | None = None
    camera_rotations: np.ndarray | None = None
    name: str = "sequence"
    joint_names: tuple[str, ...] | None = None
    edges: np.ndarray | None = None
    fps: float | None = None
    meta: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)

        p2 = as_float_array("points_2d", self.points_2d)
        if p2.ndim != 3 or p2.shape[2] != 2:
            raise shape_error("points_2d", "(F, P, 2)", p2.shape, _layout_hint(p2.shape))
        n_frames, n_points, _ = p2.shape
        if n_frames < 1 or n_points < 1:
            raise shape_error("points_2d", "at least one frame and one point", p2.shape)

        vis = None
        if self.visibility is not None:
            vis = as_float_array("visibility", self.visibility)
            if vis.shape != (n_frames, n_points):
                raise shape_error("visibility", f"(F, P) = ({n_frames}, {n_points})", vis.shape,
                                  "one weight per frame and point, 0 = missing")
            if not np.all(np.isfinite(vis)) or vis.min() < 0 or vis.max() > 1:
                raise ValidationError(
                    f"visibility: expected values in [0, 1], got range [{np.nanmin(vis):.3g}, {np.nanmax(vis):.3g}]"
                    f"{' and NaN' if not np.all(np.isfinite(vis)) else ''}; clip detector scores to [0, 1]")
        bad = ~np.isfinite(p2).all(axis=2)  # (F, P)
        if bad.any():
            visible_bad = bad if vis is None else bad & (vis > 0)
            if visible_bad.any():
                f, p = np.argwhere(visible_bad)[0]
                raise ValidationError(
                    f"points_2d: expected finite values at visible points, got NaN/inf at "
                    f"{int(visible_bad.sum())} visible entries (first: frame {f}, point {p}); "
                    "mark missing points with visibility = 0")
            p2 = np.where(bad[..., None], 0.0, p2)
        set_("points_2d", _freeze(p2))
        if vis is not None:
            set_("visibility", _freeze(vis))

        if self.points_3d is not None:
            p3 = as_float_array("points_3d", self.points_3d)
            if p3.shape != (n_frames, n_points, 3):
                raise shape_error("points_3d", f"(F, P, 3) = ({n_frames}, {n_points}, 3)", p3.shape,
                                  _layout_hint(p3.shape) if p3.ndim != 3 or p3.shape[2] != 3 else
                                  "ground truth must have the same frames and points as points_2d")
            if not np.all(np.isfinite(p3)):
                raise ValidationError("points_3d: expected finite values, got NaN/inf; drop those frames first")
            set_("points_3d", _freeze(p3))

        if self.projection not in PROJECTIONS:
            raise ValidationError(f"projection: expected one of {PROJECTIONS}, got {self.projection!r}")
        if self.intrinsics is not None:
            k = as_float_array("intrinsics", self.intrinsics)
            if k.shape not in ((3, 3), (n_frames, 3, 3)):
                raise shape_error("intrinsics", f"(3, 3) or (F, 3, 3) with F = {n_frames}", k.shape,
                                  "K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
            set_("intrinsics", _freeze(k))
        if self.camera_rotations is not None:
            r = as_float_array("camera_rotations", self.camera_rotations)
            if r.shape != (n_frames, 3, 3):
                raise shape_error("camera_rotations", f"(F, 3, 3) with F = {n_frames}", r.shape)
            if not np.isfinite(r).all():
                raise ValidationError("camera_rotations: expected finite values, got NaN or inf")
            off = np.abs(r @ r.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))  # (F,)
            det = np.linalg.det(r)
            if off.max() > 1e-4 or det.min() < 0:
                f = int(np.argmax(np.maximum(off, det < 0)))
                raise ValidationError(f"camera_rotations: expected rotation matrices (R R^T = I, det R = +1), got "
                                      f"|R R^T - I| = {off[f]:.2g}, det {det[f]:.3g} at frame {f}; pass the "
                                      "nearest rotations (nrsfm.geometry.nearest_rotation) or none")
            set_("camera_rotations", _freeze(r))
        if self.joint_names is not None:
            names = tuple(str(n) for n in self.joint_names)
            if len(names) != n_points:
                raise shape_error("joint_names", f"{n_points} names (one per point)", len(names))
            set_("joint_names", names)
        if self.edges is not None:
            e = np.asarray(self.edges)
            if e.size == 0:
                e = e.reshape(0, 2)
            if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
                raise shape_error("edges", "(E, 2) integer point indices", e.shape, "0-based index pairs")
            if e.size and (e.min() < 0 or e.max() >= n_points):
                raise ValidationError(f"edges: expected indices in [0, {n_points - 1}], got [{e.min()}, {e.max()}]; "
                                      "MATLAB lists are 1-based: subtract 1")
            set_("edges", _freeze(e.astype(np.int64)))
        if self.fps is not None:
            fps = as_float_array("fps", self.fps).ravel()
            if fps.size != 1 or not (np.isfinite(fps[0]) and fps[0] > 0):
                raise ValidationError(f"fps: expected one positive frame rate in Hz (or None), got {self.fps!r}")
            set_("fps", float(fps[0]))
        set_("name", str(self.name))
        set_("meta", {str(k): str(v) for k, v in dict(self.meta).items()})

    # ------------------------------------------------------------------ views
    @property
    def n_frames(self) -> int:
        return self.points_2d.shape[0]

    @property
    def n_points(self) -> int:
        return self.points_2d.shape[1]

    @property
    def has_ground_truth(self) -> bool:
        return self.points_3d is not None

    @property
    def weights(self) -> np.ndarray:
        """`(F, P)` visibility weights (all ones when ``visibility`` is None)."""
        if self.visibility is None:
            return np.ones((self.n_frames, self.n_points))
        return self.visibility

    @property
    def is_complete(self) -> bool:
        """True when every point is visible in every frame."""
        return self.visibility is None or bool(np.all(self.visibility > 0))

    @property
    def missing_fraction(self) -> float:
        return 0.0 if self.visibility is None else float(np.mean(self.visibility == 0))

    def replace(self, **changes: Any) -> "Sequence":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def select_frames(self, frames: slice | np.ndarray | list[int]) -> "Sequence":
        """A sequence restricted to ``frames`` (a slice or index array)."""
        idx = np.arange(self.n_frames)[frames]
        take = lambda a: None if a is None else a[idx]  # noqa: E731
        k = self.intrinsics
        if k is not None and k.ndim == 3:
            k = k[idx]
        return self.replace(points_2d=self.points_2d[idx], visibility=take(self.visibility),
                            points_3d=take(self.points_3d), camera_rotations=take(self.camera_rotations),
                            intrinsics=k)

    def select_points(self, points: slice | np.ndarray | list[int]) -> "Sequence":
        """A sequence restricted to ``points`` (a slice, index array or `(P,)` boolean mask), in that order;
        joint names follow, and edges between two kept points are renumbered (the others are dropped)."""
        idx = np.arange(self.n_points)[points]
        take = lambda a: None if a is None else a[:, idx]  # noqa: E731
        names = None if self.joint_names is None else tuple(self.joint_names[i] for i in idx)
        edges = self.edges
        if edges is not None:
            new_index = np.full(self.n_points, -1)
            new_index[idx] = np.arange(len(idx))
            e = new_index[edges]
            edges = e[(e >= 0).all(axis=1)]
        return self.replace(points_2d=self.points_2d[:, idx], visibility=take(self.visibility),
                            points_3d=take(self.points_3d), joint_names=names, edges=edges)

    def to_weak_perspective(self) -> "Sequence":
        """Perspective pixels as weak-perspective tracks, for the solvers that take orthographic ones.

        Each pixel goes through the inverse of its frame's intrinsics to normalised image coordinates
        ``(X / Z, Y / Z)``: an orthographic view of the shape scaled by ``1 / Z``, up to the perspective
        distortion of points at other depths than the shape's. The ground truth, when present, is divided by
        its frame's mean depth, so that its orthographic projection is the tracks up to that same distortion.

        Returns:
            An orthographic sequence (no intrinsics); ``meta["weak_perspective"]`` says what was done.

        Raises:
            ValidationError: the tracks are not perspective, there are no intrinsics, or a frame's ground truth
                has a mean depth <= 0 (behind the camera).
        """
        if self.projection != "perspective":
            raise ValidationError(f"to_weak_perspective: expected perspective tracks, got {self.projection} ones "
                                  f"in '{self.name}'; they need no conversion")
        if self.intrinsics is None:
            raise ValidationError(f"to_weak_perspective: '{self.name}' has perspective tracks and no intrinsics; "
                                  "pass intrinsics= (3, 3) or (F, 3, 3) to the Sequence (pixels cannot be "
                                  "normalised without them)")
        k_inv = np.linalg.inv(np.broadcast_to(self.intrinsics, (self.n_frames, 3, 3)))  # (F, 3, 3)
        # K^-1 [u, v, 1]^T; its third entry is 1 for every calibration matrix (last row 0, 0, 1)
        norm = np.einsum("fij,fpj->fpi", k_inv[:, :2, :2], self.points_2d) + k_inv[:, None, :2, 2]
        points_3d = self.points_3d
        if points_3d is not None:
            depth = points_3d[..., 2].mean(axis=1)  # (F,)
            if (depth <= 0).any():
                raise ValidationError(f"to_weak_perspective: expected the ground truth in front of the camera, "
                                      f"got a mean depth of {depth.min():.3g} in frame {int(np.argmin(depth))}")
            points_3d = points_3d / depth[:, None, None]
        meta = {**self.meta, "weak_perspective": "pixels normalised by the inverse intrinsics; ground truth "
                                                 "divided by each frame's mean depth"}
        return self.replace(points_2d=norm, points_3d=points_3d, projection="orthographic", intrinsics=None,
                            meta=meta)

    def measurement_matrix(self) -> np.ndarray:
        """The classic `(2F, P)` matrix W, rows 2f and 2f+1 holding x and y of frame f."""
        return self.points_2d.transpose(0, 2, 1).reshape(2 * self.n_frames, self.n_points).copy()

    def summary(self) -> dict[str, Any]:
        """A JSON-ready description used by ``nrsfm info``."""
        out: dict[str, Any] = {
            "name": self.name,
            "frames": self.n_frames,
            "points": self.n_points,
            "projection": self.projection,
            "ground_truth": self.has_ground_truth,
            "camera_rotations": self.camera_rotations is not None,
            "missing_fraction": round(self.missing_fraction, 6),
            "intrinsics": self.intrinsics is not None,
            "joint_names": list(self.joint_names) if self.joint_names else None,
            "edges": 0 if self.edges is None else int(self.edges.shape[0]),
            "fps": self.fps,
        }
        out.update({f"meta.{k}": v for k, v in self.meta.items()})
        return out

    # --------------------------------------------------------------- file I/O
    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the sequence as `.npz` (no pickled objects), atomically.

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is False.
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ValidationError(f"path: expected a file name ending in .npz, got {str(path)!r}")
        arrays: dict[str, np.ndarray] = {
            "format": np.array("nrsfm.Sequence"),
            "format_version": np.array(FORMAT_VERSION),
            "points_2d": self.points_2d,
            "projection": np.array(self.projection),
            "name": np.array(self.name),
        }
        for key in ("visibility", "points_3d", "intrinsics", "camera_rotations", "edges"):
            value = getattr(self, key)
            if value is not None:
                arrays[key] = value
        if self.joint_names is not None:
            arrays["joint_names"] = np.array(self.joint_names, dtype=str)
        if self.fps is not None:
            arrays["fps"] = np.array(self.fps)
        if self.meta:
            arrays["meta_keys"] = np.array(list(self.meta.keys()), dtype=str)
            arrays["meta_values"] = np.array(list(self.meta.values()), dtype=str)
        with atomic_write(path, overwrite=overwrite) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Sequence":
        """Read a sequence written by :meth:`save` (never unpickles)."""
        path = Path(path)
        arrays = read_npz(path, "an nrsfm sequence .npz")
        if "points_2d" not in arrays:
            if is_reconstruction(arrays):
                raise DataFormatError(f"{path}: expected a sequence, got a reconstruction (written by 'nrsfm solve "
                                      "--out'); read it with nrsfm.Reconstruction.load")
            raise DataFormatError(f"{path}: expected an nrsfm sequence with a 'points_2d' array, got arrays "
                                  f"{sorted(arrays)}; convert other layouts with 'nrsfm convert'")
        keys = set(arrays)
        get = arrays.get
        meta = {}
        if "meta_keys" in keys:
            meta = dict(zip(arrays["meta_keys"].tolist(), arrays["meta_values"].tolist()))
        return cls(
            points_2d=arrays["points_2d"],
            visibility=get("visibility"),
            points_3d=get("points_3d"),
            projection=str(arrays["projection"]) if "projection" in keys else "orthographic",
            intrinsics=get("intrinsics"),
            camera_rotations=get("camera_rotations"),
            name=str(arrays["name"]) if "name" in keys else path.stem,
            joint_names=tuple(arrays["joint_names"].tolist()) if "joint_names" in keys else None,
            edges=get("edges"),
            fps=arrays["fps"] if "fps" in keys else None,
            meta=meta,
        )
