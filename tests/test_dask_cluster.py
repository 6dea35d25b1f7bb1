"""``detect --scheduler``: the tiles on a real Dask cluster (one scheduler and two worker
processes on 127.0.0.1) give the local result; a worker killed mid-run leaves no half-written
output."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tunneldef.cli import main
from tunneldef.io import read

distributed = pytest.importorskip("distributed")

FIELDS = ("deformation", "deformation_horizontal", "deformation_vertical", "chainage", "lod95")
FLAGS = ("danger", "shell", "surface", "significant")
START_TIMEOUT = 60.0  # s for the cluster to come up
RUN_TIMEOUT = 600.0  # s for one detect run


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _dask(*args: str) -> list[str]:
    exe = Path(sys.executable).with_name("dask")
    return [str(exe), *args] if exe.exists() else [sys.executable, "-m", "dask", *args]


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=20)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """``tcp://127.0.0.1:PORT`` of a scheduler with two single-threaded workers (stopped at the
    end), and the worker processes."""
    log = tmp_path_factory.mktemp("dask-logs")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen(
            _dask("scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"),
            stdout=open(log / "scheduler.log", "wb"), stderr=subprocess.STDOUT, env=env))
        workers = []
        for i in range(2):
            workers.append(subprocess.Popen(
                _dask("worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                      "--nworkers", "1", "--no-dashboard", "--memory-limit", "3GB",
                      "--name", f"w{i}"),
                stdout=open(log / f"worker{i}.log", "wb"), stderr=subprocess.STDOUT, env=env))
        procs += workers
        deadline = time.monotonic() + START_TIMEOUT
        client = None
        while time.monotonic() < deadline:
            try:
                client = client or distributed.Client(address, timeout="5s")
                if len(client.scheduler_info()["workers"]) == 2:
                    break
            except OSError:
                pass
            time.sleep(0.5)
        else:
            pytest.fail(f"the Dask cluster did not start; see {log}")
        client.close()
        yield address, workers
    finally:
        _stop(procs)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    assert main(["synth", str(folder), "--length", "30", "--density", "80", "--chamber",
                 "--format", "laz", "--quiet"]) == 0
    return folder / "ref.laz", folder / "cmp.laz"


@pytest.fixture(scope="module")
def local_result(pair, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "out.laz"
    assert main(["detect", str(pair[0]), str(pair[1]), "-o", str(out), "--tile-length", "8",
                 "--quiet"]) == 0
    return read(out)


def _detect(pair, out: Path, address: str, tile_dir: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    return subprocess.Popen(
        [sys.executable, "-c", "import sys; from tunneldef.cli import main; sys.exit(main())",
         "detect", str(pair[0]), str(pair[1]), "-o", str(out), "--tile-length", "8",
         "--scheduler", address, "--tile-dir", str(tile_dir), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)


def _assert_same(a, b) -> None:
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert sorted(a.fields) == sorted(b.fields)
    for name in FIELDS:
        x, y = a.fields[name].astype(np.float64), b.fields[name].astype(np.float64)
        np.testing.assert_array_equal(np.isnan(x), np.isnan(y), err_msg=name)
        assert np.nanmax(np.abs(x - y), initial=0.0) <= 1e-6, name
    for name in FLAGS:
        np.testing.assert_array_equal(a.fields[name], b.fields[name], err_msg=name)


def test_cluster_run_equals_local(cluster, pair, local_result, tmp_path) -> None:
    address, _ = cluster
    out = tmp_path / "out.laz"
    proc = _detect(pair, out, address, tmp_path)
    _, err = proc.communicate(timeout=RUN_TIMEOUT)
    assert proc.returncode == 0, err.decode()
    _assert_same(read(out), local_result)
    assert not list(tmp_path.glob("tunneldef-tiles-*")), "the tiles' folder is removed"


def test_killed_worker_retried_or_one_line_error(cluster, pair, local_result, tmp_path) -> None:
    address, workers = cluster
    out = tmp_path / "out.laz"
    proc = _detect(pair, out, address, tmp_path)
    deadline = time.monotonic() + RUN_TIMEOUT
    while not list(tmp_path.glob("tunneldef-tiles-*/tile_*/cmp_mask.npy")):
        assert proc.poll() is None, proc.communicate()[1].decode()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    workers[0].send_signal(signal.SIGKILL)  # mid-run: the tiles' first pass is under way
    _, err = proc.communicate(timeout=RUN_TIMEOUT)
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.laz")]
    assert not leftovers, "no temporary output is left behind"
    if proc.returncode == 0:  # the scheduler ran the lost tiles again on the other worker
        _assert_same(read(out), local_result)
    else:
        text = err.decode()
        errors = [x for x in text.splitlines() if x.startswith("tunneldef: error:")]
        assert len(errors) == 1 and text.strip().endswith(errors[0]), text
        assert "Traceback" not in text, text
        assert not out.exists(), "the output is never half written"


def test_unreachable_scheduler_is_a_one_line_error(pair, tmp_path, capsys) -> None:
    out = tmp_path / "out.laz"
    code = main(["detect", str(pair[0]), str(pair[1]), "-o", str(out), "--scheduler",
                 f"tcp://127.0.0.1:{_free_port()}", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("tunneldef: error: cannot reach the Dask scheduler")
    assert not out.exists()
