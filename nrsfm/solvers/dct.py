"""The DCT trajectory basis of CSF2 and its weighted Gram matrices from cosine sums."""

from __future__ import annotations

import functools

import numpy as np
from numpy.lib.stride_tricks import as_strided


def dct_basis(n_frames: int, d: int) -> np.ndarray:
    """`(F, d)` orthonormal DCT-II basis (first column constant)."""
    t = np.arange(n_frames)
    k = np.arange(d)
    basis = np.cos(np.pi * (2 * t[:, None] + 1) * k[None] / (2 * n_frames))
    basis[:, 0] *= 1 / np.sqrt(2)
    return basis * np.sqrt(2 / n_frames)


@functools.lru_cache(maxsize=8)
def _dct_cosines(n_frames: int, d: int) -> np.ndarray:
    """`(2d - 1, F)` ``cos(pi m (2f + 1) / 2F)`` for m < 2d - 1 (read-only; cached: CSF2's missing-data
    rounds need them thousands of times on one sequence)."""
    freq = np.arange(2 * d - 1)
    cos = np.cos(np.pi * (2 * np.arange(n_frames)[None] + 1) * freq[:, None] / (2 * n_frames))
    cos.flags.writeable = False
    return cos


def dct_weighted_gram(weights: np.ndarray, d: int) -> np.ndarray:
    """``G[a, b] = sum_f omega_fa omega_fb weights_f`` `(d, d, ...)` for the DCT basis of :func:`dct_basis` and
    `(F, ...)` weights, from ``2d - 1`` cosine sums (``cos x cos y = (cos(x + y) + cos(x - y)) / 2``): ``O(F d)``
    products instead of ``O(F d^2)``.
    """
    sums, scale = _dct_cosine_sums(weights, d)
    sums = sums.reshape((2 * d - 1,) + weights.shape[1:])
    a = np.arange(d)
    gram = 0.5 * (sums[a[:, None] + a[None]] + sums[np.abs(a[:, None] - a[None])])
    return gram * (scale[:, None] * scale[None]).reshape((d, d) + (1,) * (weights.ndim - 1))


def _dct_cosine_sums(weights: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``2d - 1`` cosine sums `(2d - 1, prod(weights.shape[1:]))` of `(F, ...)` weights and the `(d,)` scale of
    the DCT basis vectors (:func:`dct_basis`)."""
    n_frames = weights.shape[0]
    scale = np.full(d, np.sqrt(2 / n_frames))
    scale[0] = np.sqrt(1 / n_frames)
    return _dct_cosines(n_frames, d) @ weights.reshape(n_frames, -1), scale


def dct_weighted_gram_blocks(weights: np.ndarray, d: int) -> np.ndarray:
    """`dct_weighted_gram` of `(F, K, K)` weights laid out as the `(d K, d K)` matrix with entry
    ``[(a, k), (b, l)]`` = ``G[a, b, k, l]``: CSF2's X-step normal matrix. The ``a + b`` (Hankel) and ``|a - b|``
    (Toeplitz) terms are strided views of the cosine sums, added straight into that layout (the same values to the
    bit as :func:`dct_weighted_gram`).
    """
    k = weights.shape[1]
    sums, scale = _dct_cosine_sums(weights, d)
    sums = sums.reshape(2 * d - 1, k, k)
    s0, s1, s2 = sums.strides
    plus = as_strided(sums, shape=(d, k, d, k), strides=(s0, s1, s0, s2), writeable=False)  # [a, k, b, l]: a + b
    # |a - b| as b - a + d - 1 in the mirrored sums (entry m = sums[|m - (d - 1)|]), read from their middle
    mirrored = np.concatenate([sums[d - 1:0:-1], sums[:d]])[d - 1:]
    minus = as_strided(mirrored, shape=(d, k, d, k), strides=(-s0, s1, s0, s2), writeable=False)
    gram = np.add(plus, minus)
    gram *= (0.5 * scale[:, None] * scale[None])[:, None, :, None]  # halving is exact: as (x * 0.5) * (s_a s_b)
    return gram.reshape(d * k, d * k)
