"""Keep large temporary arrays on the heap while a solver runs (glibc only; a no-op elsewhere).

glibc serves every allocation above its mmap threshold (at most 32 MiB by default) with a fresh ``mmap`` and
returns it with ``munmap`` when freed, so a solver that allocates and frees the same large temporaries in every
iteration spends much of its time in the kernel zeroing new pages. :func:`large_arrays_on_heap` raises the mmap
and trim thresholds for the duration of a solve and then sets them to 32 / 64 MiB, the values glibc's own dynamic
rule settles at after large frees.
"""

from __future__ import annotations

import contextlib
import ctypes
import platform
from collections.abc import Iterator

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_AFTER = (32 << 20, 64 << 20)  # glibc's dynamic maximum of the mmap threshold, and twice it for trimming


def _glibc():
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


@contextlib.contextmanager
def large_arrays_on_heap(threshold: int = 256 << 20) -> Iterator[bool]:
    """Serve allocations below ``threshold`` bytes from the heap and keep freed heap memory for reuse; yields
    whether the setting took effect (False where the C library is not glibc)."""
    libc = _glibc()
    ok = bool(libc is not None and libc.mallopt(_M_MMAP_THRESHOLD, threshold)
              and libc.mallopt(_M_TRIM_THRESHOLD, 2 * threshold))
    try:
        yield ok
    finally:
        if ok:
            libc.mallopt(_M_MMAP_THRESHOLD, _AFTER[0])
            libc.mallopt(_M_TRIM_THRESHOLD, _AFTER[1])
