"""Assertions shared by the script-mode and the GUI tests: what CloudCompare holds after an
action against what the core computed on the same files."""

from __future__ import annotations

import numpy as np

#: float32 local coordinates of a few tens of metres after the global shift: ~4e-6 m steps.
XYZ_TOL = 1e-4
#: A cloud moved in place goes through CloudCompare's float32 ``ccGLMatrix`` (its translation
#: is hundreds of metres in local coordinates): 0.13 mm measured on the test pair.
MOVED_TOL = 1e-3


def assert_fields_equal_core(fields: dict[str, np.ndarray], result) -> None:
    """Every field the core returned is on the cloud with the core's values (float32)."""
    from tunneldef_cloudcompare.jobs import OPTIONAL_FIELDS

    from tunneldef.pipeline import OUTPUT_FIELDS

    expected = [*OUTPUT_FIELDS, *(f for f in OPTIONAL_FIELDS if f in result.cloud.fields)]
    assert sorted(fields) == sorted(expected)
    for name in expected:
        want = np.asarray(result.cloud.fields[name], dtype=np.float32).astype(np.float64)
        got = fields[name]
        assert got.shape == want.shape, name
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6, equal_nan=True, err_msg=name)
    d = fields["deformation"]
    assert np.isfinite(d).mean() > 0.8  # a real result, not an all-NaN field
    assert np.nanmin(d) < -0.02  # the 50 mm roof sag is in it


def assert_xyz(got: np.ndarray, want: np.ndarray, what: str, tol: float = XYZ_TOL) -> None:
    """Same points, same order, within ``tol`` metres."""
    assert got.shape == want.shape, what
    err = float(np.abs(got - want).max())
    assert err < tol, f"{what}: max |difference| {err:.3g} m"


def assert_red_white_blue(
    rgb: dict[str, list[int]], inside: tuple[bool, bool, bool, bool, bool] = (True,) * 5
) -> None:
    """Colours at -limit, -limit/2, 0, +limit/2, +limit (keys in that order): red, pink,
    white, light blue, blue (CloudCompare quantises the ramp: +-3 per channel). ``inside``
    says which of the five values lie within the field's own range: CloudCompare colours only
    those by the ramp (and clamps the saturation to the field's largest |value|)."""
    cols = [np.array(c) for c in rgb.values()]
    assert len(cols) == 5
    want = ([255, 0, 0], [255, 127, 127], [255, 255, 255], [127, 127, 255], [0, 0, 255])
    tols = (3, 6, 6, 6, 3)
    for col, w, tol, ok in zip(cols, want, tols, inside, strict=True):
        if ok:
            np.testing.assert_allclose(col, w, atol=tol)


def samples_inside(values: np.ndarray, limit: float) -> tuple[bool, ...]:
    """Which of -limit, -limit/2, 0, +limit/2, +limit lie within the finite values' range."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    lo, hi = float(v.min()), float(v.max())
    return tuple(lo - 1e-9 <= f * limit <= hi + 1e-9 for f in (-1.0, -0.5, 0.0, 0.5, 1.0))
