"""Shared fixtures: the real dataset (skipped where ../shared is absent) and a seeded rng."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
REAL_DATASET = REPO_ROOT.parent / "shared" / "datasets" / "1b-3D-Camera-Localization.g2o"


@pytest.fixture
def real_dataset_path() -> Path:
    """The third-party course dataset, read in place from ../shared; never copied."""
    if not REAL_DATASET.is_file():
        pytest.skip("the real dataset ../shared/datasets is not present on this machine")
    return REAL_DATASET


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)
