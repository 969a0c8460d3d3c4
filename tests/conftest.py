"""Shared fixtures. Real-data tests read ``$NRSFM_DATA`` (the ``real_data`` fixture), skipped when it is absent."""

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


def _real_data(*parts: str) -> Path:
    """``$NRSFM_DATA/<parts>`` or a skip naming what is missing.

    A folder or file under the data root may be absent (the shared copy leaves some out), so its test skips. A root
    that is unset or not a folder while ``NRSFM_REQUIRE_DATA=1`` (``.ci/run`` sets it when the data lies beside the
    checkout) fails the test instead, so that real-data tests cannot skip silently when the data should be there.
    """
    root = os.environ.get("NRSFM_DATA")
    if not root or not Path(root).is_dir():
        reason = ("NRSFM_DATA is not set" if not root else f"NRSFM_DATA={root} is not a folder")
        if os.environ.get("NRSFM_REQUIRE_DATA") == "1":
            pytest.fail(f"{reason}, but NRSFM_REQUIRE_DATA=1 says the real data should be there", pytrace=False)
        pytest.skip(f"{reason}: real-data test")
    path = Path(root).joinpath(*parts)
    if not path.exists():
        pytest.skip(f"NRSFM_DATA={root} has no {'/'.join(parts)}")
    return path


@pytest.fixture
def real_data():
    """:func:`_real_data`: ``real_data("surreal", "sample")`` is that path under ``$NRSFM_DATA``, or a skip."""
    return _real_data


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    return _real_data("nrsfm")


@pytest.fixture(scope="session")
def h36m_dir() -> Path:
    return _real_data("h36m")


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
