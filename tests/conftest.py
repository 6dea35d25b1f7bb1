"""Shared fixtures: paths to the real scans in ../shared/data (skipped where absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
DRIFT_LAZ = SHARED_DATA / "freiberg_mine_drift_tls.laz"
CHAMBER_LAZ = SHARED_DATA / "freiberg_mine_chamber_tls_0005.laz"
DRIFT_POINTS = 2_679_087
CHAMBER_POINTS = 2_784_434


@pytest.fixture(scope="session")
def drift_path() -> Path:
    if not DRIFT_LAZ.is_file():
        pytest.skip(f"real scan not present: {DRIFT_LAZ}")
    return DRIFT_LAZ


@pytest.fixture(scope="session")
def chamber_path() -> Path:
    if not CHAMBER_LAZ.is_file():
        pytest.skip(f"real scan not present: {CHAMBER_LAZ}")
    return CHAMBER_LAZ
