"""Shared test fixtures.

Tests that need the real LiDAR scans in ``../shared/data`` request the ``shared_data`` fixture;
when the folder is absent they skip with a reason that says where the data was looked for.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("ci", max_examples=60, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=60, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

REPO_ROOT = Path(__file__).resolve().parents[1]


def _shared_data_dir() -> Path:
    env = os.environ.get("GRAFFMATCH_SHARED_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data (or $GRAFFMATCH_SHARED_DATA); skips when it is absent."""
    path = _shared_data_dir()
    if not (path / "kitti00_first6").is_dir():
        pytest.skip(f"real LiDAR data not found at {path} (set GRAFFMATCH_SHARED_DATA)")
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
