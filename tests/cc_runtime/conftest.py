"""Fixtures for the tests in the real CloudCompare 2.13 + PythonRuntime (marker
``cloudcompare``; select them with ``-m cloudcompare``, leave them out with
``-m "not cloudcompare"``). They skip, saying why, only when the shared build is absent."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from .runner import Unavailable, find_runtime, write_pair


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "cloudcompare: runs inside the real CloudCompare 2.13 + PythonRuntime "
        "(../shared/cloudcompare-python); skipped when that build is absent",
    )


@pytest.fixture(scope="session")
def cc_runtime():
    """The real CloudCompare runtime (unpacked from the shared tarball if needed)."""
    try:
        return find_runtime()
    except Unavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="session")
def cc_pair(tmp_path_factory) -> tuple[Path, Path]:
    """``ref.ply``, ``cmp.ply``: a 22 k-point synthetic pair in survey coordinates."""
    return write_pair(tmp_path_factory.mktemp("cc_pair"))


@pytest.fixture(scope="session")
def core(cc_pair) -> SimpleNamespace:
    """What ``tunneldef detect`` (the core, default parameters) gives on the same files."""
    from tunneldef.io import read
    from tunneldef.pipeline import detect

    ref, cmp = read(cc_pair[0]), read(cc_pair[1])
    return SimpleNamespace(ref=ref, cmp=cmp, result=detect(ref, cmp))


def load_run(workdir: Path, proc) -> SimpleNamespace:
    """The report and arrays a run left in ``workdir`` (an assertion error shows the log)."""
    log = (proc.stdout or "")[-3000:] + (proc.stderr or "")[-3000:]
    report_path = workdir / "report.json"
    assert report_path.is_file(), f"CloudCompare exited {proc.returncode} without a report:\n{log}"
    report = json.loads(report_path.read_text(encoding="utf-8"))
    arrays_path = workdir / "arrays.npz"
    arrays = dict(np.load(arrays_path)) if arrays_path.is_file() else {}
    return SimpleNamespace(proc=proc, report=report, arrays=arrays, log=log)
