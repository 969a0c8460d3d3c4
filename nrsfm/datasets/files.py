"""Reading a sequence from any supported file: an nrsfm `.npz` or a CMU NRSfM `.mat`."""

from __future__ import annotations

import os
from pathlib import Path

from nrsfm.datasets.cmu import load_cmu_mat
from nrsfm.errors import DataFormatError
from nrsfm.sequence import Sequence


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Read a :class:`~nrsfm.sequence.Sequence` from `.npz` or a CMU `.mat` file.

    `.npz` files must be nrsfm sequences (see :meth:`Sequence.save`); `.mat`
    files may be in the Akhter layout (``W``, ``S``, ``Rs``) or the PND layout
    (``X`` of shape 3 x P x F).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise DataFormatError(f"{path}: expected a file, got a directory")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return Sequence.load(path)
    if suffix == ".mat":
        return load_cmu_mat(path)
    raise DataFormatError(f"{path}: expected a .npz sequence or a CMU NRSfM .mat file, got a '{suffix or 'no'}' "
                          "extension")
