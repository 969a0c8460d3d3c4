"""The classic CMU NRSfM benchmark `.mat` files (Akhter and PND layouts)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nrsfm.converters import from_akhter, from_pnd
from nrsfm.errors import DataFormatError
from nrsfm.sequence import Sequence

#: The sequences of the classic benchmark, in the order of the published tables.
CMU_SEQUENCES = ("drink", "pickup", "yoga", "stretch", "dance", "walking", "face", "jaws_rearranged")


def load_cmu_mat(path: str | os.PathLike, *, name: str | None = None) -> Sequence:
    """Load a CMU NRSfM `.mat` file in the Akhter or the PND layout.

    Akhter: ``W`` `(2F, P)`, ``S`` `(3F, P)` world frame, optional ``Rs``
    `(2F, 3)`, ``scale`` and 1-based ``list`` bones; converted with
    :func:`nrsfm.converters.from_akhter` (ground truth moved into the camera
    frame, rotations kept for the object-frame e3D). PND: ``X`` `(3, P, F)`.
    """
    import scipy.io

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        mat = scipy.io.loadmat(str(path))
    except NotImplementedError:
        raise DataFormatError(f"{path}: MATLAB v7.3 (HDF5) files are not supported by scipy; re-save it with "
                              "save(..., '-v7') in MATLAB or Octave") from None
    except Exception as exc:
        raise DataFormatError(f"{path}: expected a MATLAB .mat file, could not read it ({exc})") from None
    keys = sorted(k for k in mat if not k.startswith("__"))
    name = name or path.stem
    if "W" in mat:
        edges = mat.get("list")
        if edges is not None and (edges.ndim != 2 or edges.shape[1] != 2):
            edges = None
        scale = mat.get("scale")
        return from_akhter(mat["W"], mat.get("S"), mat.get("Rs"), name=name, scale=scale, edges=edges)
    if "X" in mat and np.ndim(mat["X"]) == 3:
        return from_pnd(mat["X"], name=name)
    raise DataFormatError(f"{path}: expected the Akhter layout (W, S, Rs) or the PND layout (X, 3 x P x F), got "
                          f"variables {keys}")


def list_cmu_sequences(folder: str | os.PathLike) -> list[Path]:
    """The `.mat` files of a benchmark folder, known sequences first in table order."""
    folder = Path(folder)
    files = sorted(folder.glob("*.mat"))
    order = {n: i for i, n in enumerate(CMU_SEQUENCES)}
    return sorted(files, key=lambda p: (order.get(p.stem, len(order)), p.stem))
