"""Every field ``detect`` writes on two fixed pairs, bit for bit against ``golden/golden.json``.

A refactor must not move a single bit; a change meant to move results regenerates the file with
``python tests/golden/make_golden.py`` and says why in its commit.
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
def test_detect_is_bit_identical(name: str) -> None:
    got = fingerprint(pairs()[name])
    want = EXPECTED[name]
    assert sorted(got["fields"]) == sorted(want["fields"])
    for field, w in want["fields"].items():
        g = got["fields"][field]
        assert g["dtype"] == w["dtype"], field
        assert g["sha256"] == w["sha256"], (
            f"{field} changed: first values {g['head']} vs {w['head']}"
        )
    np.testing.assert_array_equal(np.asarray(got["transform"]), np.asarray(want["transform"]))
    assert (got["zones"], got["sections"]) == (want["zones"], want["sections"])
