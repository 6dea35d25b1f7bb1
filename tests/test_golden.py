"""Every field ``detect`` writes on two fixed pairs, against ``golden/golden.json``.

A refactor must not move results; a change meant to move them regenerates the file with
``python tests/golden/make_golden.py`` and says why in its commit. Each field is compared by its
hash (bit for bit) and, where the hash differs, by its NaN count and sums, which must agree to
1e-9 m per point: threaded reductions (KD-tree queries, Open3D's searches) may order a sum
differently from run to run, which moves the last bits but never a value a surveyor reads.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).resolve().parent / "golden"
sys.path.insert(0, str(GOLDEN))

from make_golden import fingerprint, pairs  # noqa: E402

pytestmark = pytest.mark.slow

EXPECTED = json.loads((GOLDEN / "golden.json").read_text(encoding="utf-8"))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_detect_matches_the_saved_fingerprints(name: str) -> None:
    got = fingerprint(pairs()[name])
    want = EXPECTED[name]
    assert sorted(got["fields"]) == sorted(want["fields"])
    for field, w in want["fields"].items():
        g = got["fields"][field]
        assert g["dtype"] == w["dtype"], field
        if g["sha256"] == w["sha256"]:
            continue
        points = got["points"]
        assert g["nan"] == w["nan"], f"{field}: {g['nan']} NaN vs {w['nan']}"
        assert abs(g["sum"] - w["sum"]) <= 1e-9 * points, (field, g["sum"], w["sum"])
        assert abs(g["abs_sum"] - w["abs_sum"]) <= 1e-9 * points, (
            field, g["abs_sum"], w["abs_sum"]
        )
        np.testing.assert_allclose(g["head"], w["head"], rtol=0, atol=1e-6, err_msg=field)
    np.testing.assert_allclose(np.asarray(got["transform"]), np.asarray(want["transform"]),
                               rtol=0, atol=1e-9)
    assert (got["zones"], got["sections"]) == (want["zones"], want["sections"])
