"""Shared fixtures. Real-data tests read ``$NRSFM_DATA`` and are skipped when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

# derandomize: CI runs the same examples every time (a failure reproduces; no flaky landings)
settings.register_profile("nrsfm", deadline=None, max_examples=40, derandomize=True)
settings.load_profile("nrsfm")


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


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
