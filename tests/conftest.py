"""Shared fixtures: paths to the real scans in ../shared/data (skipped where absent)."""

from __future__ import annotations

import os
from pathlib import Path

# Under pytest-xdist each worker shares the machine's cores with the others, and its own
# Dask threads already fill them: OpenMP's threads (Open3D's normals and ICP) then only wait
# on each other. One OpenMP thread per worker ran four heavy test files in 242 s instead of
# 297 s on 2 cores with 2 workers (user time 451 s instead of 566 s), with the same results.
# Set before any test imports Open3D; a value the caller set stays.
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    os.environ.setdefault("OMP_NUM_THREADS", "1")

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
