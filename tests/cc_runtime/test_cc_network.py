"""The plugin on a drift network in the real CloudCompare, command-line mode: *Extract
centerline* and *Detect deformation* find the network from the plan by themselves, draw one
polyline per edge and write the ``branch`` field, equal to the core on the same files."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from .checks import assert_xyz
from .conftest import load_run
from .runner import HERE, write_network_pair

pytestmark = pytest.mark.cloudcompare


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return write_network_pair(tmp_path_factory.mktemp("cc_network_pair"))


@pytest.fixture(scope="module")
def run(cc_runtime, files, tmp_path_factory):
    work = tmp_path_factory.mktemp("cc_network")
    proc = cc_runtime.run_script(
        HERE / "script_actions.py", list(files), workdir=work,
        env_extra={"TDCC_OUT": str(work), "TDCC_ACTIONS": "centerline,detect"},
    )
    return load_run(work, proc)


@pytest.fixture(scope="module")
def core(files):
    from tunneldef.centerline.network import extract_network
    from tunneldef.io import read
    from tunneldef.pipeline import detect_network

    ref, cmp = read(files[0]), read(files[1])
    return SimpleNamespace(network=extract_network(ref.xyz).network,
                           result=detect_network(ref, cmp))


def test_one_polyline_per_edge_and_the_branch_field(run, core):
    assert run.proc.returncode == 0, run.log
    assert run.report.get("finished") and run.report["errors"] == [], run.report["errors"]
    centerline, detect = run.report["actions"]
    edges = core.network.edges
    assert len(edges) == 3 and len(centerline["names"]) == 3
    for k, edge in enumerate(edges):
        assert f"edge {edge.id} " in centerline["names"][k]
        assert_xyz(run.arrays[f"centerline:{k}"], edge.centerline.points, f"edge {k}", tol=1e-3)
    res = core.result
    n_ref, n_cmp = len(res.ref_network.edges), len(res.cmp_network.edges)
    assert len(detect["polylines"]) == n_ref + n_cmp
    for k, edge in enumerate(res.ref_network.edges):
        assert_xyz(run.arrays[f"ref_line:{k}"], edge.centerline.points, f"ref edge {k}",
                   tol=1e-3)
    for k, edge in enumerate(res.cmp_network.edges):
        assert_xyz(run.arrays[f"cmp_line:{k}"], edge.centerline.points, f"cmp edge {k}",
                   tol=1e-3)
    branch = run.arrays["field:branch"]
    want = np.asarray(res.cloud.fields["branch"], dtype=np.float64)
    np.testing.assert_array_equal(branch, want)
    assert len(np.unique(branch[branch < 65535])) == 3  # every branch measured
    d = run.arrays["field:deformation"]
    np.testing.assert_allclose(
        d, np.asarray(res.cloud.fields["deformation"], dtype=np.float32), atol=1e-6,
        equal_nan=True)
