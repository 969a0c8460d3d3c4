"""What every solver returns: :class:`Reconstruction`, with its `.npz` save and load."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nrsfm.errors import DataFormatError, SolverError, ValidationError, shape_error
from nrsfm.io import RECONSTRUCTION_ARRAYS, atomic_write, read_npz


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """What every solver returns.

    Attributes:
        points_3d: `(F, P, 3)` reconstructed shapes in the camera frame,
            centred per frame (orthographic depth is known up to a global sign).
        rotations: `(F, 3, 3)` camera rotations, ``points_3d[f].T = R_f S_f``
            with ``S_f`` the shape in the solver's object frame; None when the
            method has no notion of cameras.
        method: registry name; params: the parameters used, as a dict.
        iterations, converged, runtime_s, seed: run information.
        info: further method-specific numbers (final cost, chosen K, ...).
    """

    points_3d: np.ndarray
    rotations: np.ndarray | None
    method: str
    params: dict[str, Any] = field(default_factory=dict)
    iterations: int = 0
    converged: bool = True
    runtime_s: float = 0.0
    seed: int | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        x = np.asarray(self.points_3d, dtype=np.float64)
        if x.ndim != 3 or x.shape[2] != 3:
            raise shape_error("Reconstruction.points_3d", "(F, P, 3)", x.shape)
        if not np.isfinite(x).all():
            raise SolverError(f"{self.method}: the solver produced NaN/inf shapes; this is a bug, please report it "
                              "with the input file")
        object.__setattr__(self, "points_3d", x)
        if self.rotations is not None:
            r = np.asarray(self.rotations, dtype=np.float64)
            if r.shape != (x.shape[0], 3, 3):
                raise shape_error("Reconstruction.rotations", f"(F, 3, 3) with F = {x.shape[0]}", r.shape)
            object.__setattr__(self, "rotations", r)

    @property
    def shapes_object(self) -> np.ndarray:
        """`(F, P, 3)` shapes in the solver's object frame (``R^T X``)."""
        if self.rotations is None:
            raise ValidationError(f"{self.method}: this reconstruction has no camera rotations")
        return np.einsum("fpi,fij->fpj", self.points_3d, self.rotations)

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write as `.npz` (no pickles), atomically; never overwrites unless asked."""
        arrays = {"points_3d": self.points_3d, "method": np.array(self.method),
                  "run": np.array(json.dumps({"params": self.params, "iterations": self.iterations,
                                              "converged": self.converged, "runtime_s": self.runtime_s,
                                              "seed": self.seed, "info": self.info}, default=str))}
        if self.rotations is not None:
            arrays["rotations"] = self.rotations
        path = Path(path)
        with atomic_write(path, overwrite=overwrite) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Reconstruction":
        """Read a reconstruction written by :meth:`save` (``nrsfm solve FILE --out REC.npz``; never unpickles)."""
        arrays = read_npz(path, "an nrsfm reconstruction .npz")
        if not RECONSTRUCTION_ARRAYS <= set(arrays):
            hint = "; it is a sequence: read it with nrsfm.load_sequence" if "points_2d" in arrays else ""
            raise DataFormatError(f"{path}: expected a reconstruction written by 'nrsfm solve --out' (arrays "
                                  f"points_3d, method, run), got arrays {sorted(arrays)}{hint}")
        try:
            run = json.loads(str(arrays["run"]))
        except ValueError as exc:
            raise DataFormatError(f"{path}: the 'run' record is not JSON ({exc})") from None
        return cls(points_3d=arrays["points_3d"], rotations=arrays.get("rotations"), method=str(arrays["method"]),
                   params=run.get("params", {}), iterations=int(run.get("iterations", 0)),
                   converged=bool(run.get("converged", True)), runtime_s=float(run.get("runtime_s", 0.0)),
                   seed=run.get("seed"), info=run.get("info", {}))

