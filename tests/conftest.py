"""Shared fixtures. Real-data tests read ``$NRSFM_DATA`` and are skipped when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):  # one worker per core: one BLAS, OpenMP and torch thread each, as the
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # benchmarks' parallel jobs
        os.environ.setdefault(_var, "1")

import numpy as np
import pytest
from hypothesis import settings

# derandomize: CI runs the same examples every time (a failure reproduces; no flaky landings)
settings.register_profile("nrsfm", deadline=None, max_examples=40, derandomize=True)
settings.load_profile("nrsfm")

_approx = pytest.approx


def _approx_of_numbers(expected, *args, **kwargs):
    """``pytest.approx`` refusing torch tensors on every pytest version (pytest 9 iterates the expected value, which
    fails on a 0-d tensor, older releases accept it): compare ``float(t)`` or ``t.numpy()`` instead."""
    if type(expected).__module__.split(".")[0] == "torch":
        raise TypeError(f"pytest.approx: expected a number or NumPy array, got {type(expected).__name__}; "
                        "compare float(t) or t.numpy()")
    return _approx(expected, *args, **kwargs)


pytest.approx = _approx_of_numbers


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):  # pools already started before the variables above took effect
        import torch
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
        torch.set_num_threads(1)


def _data_dir(name: str) -> Path | None:
    root = os.environ.get("NRSFM_DATA")
    if not root:
        return None
    path = Path(root) / name
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    path = _data_dir("nrsfm")
    if path is None:
        pytest.skip("NRSFM_DATA/nrsfm not available")
    return path


@pytest.fixture(scope="session")
def h36m_dir() -> Path:
    path = _data_dir("h36m")
    if path is None:
        pytest.skip("NRSFM_DATA/h36m not available")
    return path


@pytest.fixture(autouse=True)
def _no_remembered_solutions(monkeypatch):
    """Each test starts with no reconstructions kept from another (:func:`nrsfm.solvers.starts.remember_solution`)."""
    from nrsfm.solvers import starts

    monkeypatch.setattr(starts, "_SOLUTIONS", type(starts._SOLUTIONS)())


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def _central_differences(value, x, h: float = 1e-6):
    """Central finite differences of the scalar ``value(x)`` for every entry of the torch tensor ``x``."""
    import torch

    fd = torch.zeros_like(x)
    for idx in np.ndindex(*x.shape):
        xp, xm = x.clone(), x.clone()
        xp[idx] += h
        xm[idx] -= h
        fd[idx] = (value(xp) - value(xm)) / (2 * h)
    return fd


@pytest.fixture
def central_differences():
    """``central_differences(value, x, h=1e-6)``: the finite-difference gradient of a scalar function of a tensor."""
    return _central_differences
