"""File helpers: atomic writes and `.npz` reading that never unpickles."""

from __future__ import annotations

import contextlib
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from nrsfm.errors import DataFormatError


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    Nothing is written to ``path`` if the body raises, and an existing file is
    never replaced unless ``overwrite`` is True.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: the file exists; pass --force (overwrite=True) to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


#: The arrays that mark an `.npz` written by :meth:`nrsfm.Reconstruction.save` (``nrsfm solve --out``).
RECONSTRUCTION_ARRAYS = frozenset({"points_3d", "method", "run"})


def is_reconstruction(names) -> bool:
    """Whether an `.npz` with these array names is a reconstruction rather than a sequence."""
    return "points_2d" not in names and RECONSTRUCTION_ARRAYS <= set(names)


def read_npz(path: str | os.PathLike, what: str) -> dict:
    """Every array of an `.npz` file as a dict, never unpickling; a :class:`DataFormatError` naming ``what``
    the file was expected to be when it is missing, not a zip of arrays, damaged or holds pickled objects."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file() or not zipfile.is_zipfile(path):
        raise DataFormatError(f"{path}: expected an .npz archive (a zip of .npy arrays), got another kind of file")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}  # read lazily: a pickled array fails here
    except ValueError as exc:
        raise DataFormatError(f"{path}: expected {what} of plain arrays, got a pickled (object) array; save numeric "
                              f"arrays ({exc})") from None
    except Exception as exc:  # zipfile.BadZipFile, OSError, ...
        raise DataFormatError(f"{path}: expected {what}, could not read it ({exc})") from None
