"""Where real datasets live: ``root`` argument, else ``$NRSFM_DATA``."""

from __future__ import annotations

import os
from pathlib import Path

from nrsfm.errors import DataFormatError

ENV_VAR = "NRSFM_DATA"


def data_root(root: str | os.PathLike | None = None) -> Path | None:
    """The data folder: ``root`` if given, else ``$NRSFM_DATA``, else None."""
    if root is not None:
        return Path(root).expanduser()
    env = os.environ.get(ENV_VAR)
    return Path(env).expanduser() if env else None


def find_dataset(name: str, root: str | os.PathLike | None = None, *, required: bool = True) -> Path | None:
    """The folder ``<root>/<name>`` (e.g. ``nrsfm``, ``h36m``).

    Raises:
        DataFormatError: when ``required`` and the folder does not exist; the
            message says how to point the toolbox at the data.
    """
    base = data_root(root)
    path = None if base is None else base / name
    if path is not None and path.is_dir():
        return path
    if not required:
        return None
    where = f"{path}" if path is not None else f"nowhere (${ENV_VAR} is not set)"
    raise DataFormatError(f"{name}: expected a dataset folder, looked in {where}; pass --root DIR or set "
                          f"{ENV_VAR}=DIR where DIR/{name} holds the files (see README: Datasets)")
