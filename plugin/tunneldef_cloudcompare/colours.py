"""The deformation colour scale: Red > White > Blue centred on 0, red = into the tunnel.

Shared by the plugin and the scripts in ``cloudcompare_scripts/`` (which import it without
CloudCompare: nothing here imports ``pycc`` at import time).
"""

from __future__ import annotations

import logging
import os
import tempfile
from typing import Any

import numpy as np

from .fields import sf_index
from .runtime import pycc_module, try_call

log = logging.getLogger(__name__)

__all__ = [
    "SCALE_NAME",
    "SCALE_UUID",
    "SCALE_RED_IN",
    "SCALE_BLUE_IN",
    "SCALE_DEFAULT",
    "symmetric_limit",
    "color_scale_xml",
    "red_white_blue_scale",
    "show_diverging",
]


def symmetric_limit(
    values: np.ndarray,
    *,
    threshold: float = 0.0,
    percentile: float = 98.0,
) -> float:
    """Half-width of a colour scale centred on 0, metres.

    The ``percentile`` of |values| (so a few outliers do not wash out the colours), at least
    ``threshold`` (so the danger level is always inside the scale) and at least 1 mm.
    """
    v = np.abs(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    lim = float(np.percentile(v, percentile)) if v.size else 0.0
    return max(lim, float(threshold), 1e-3)


#: Name and fixed identity of the plugin's colour scale (a re-run replaces it, never duplicates).
SCALE_NAME = "tunneldef deformation (red = into the tunnel)"
SCALE_UUID = "{5b7c2f4e-1d0a-4f3e-9a61-7e2d8c3b9f02}"

#: What :func:`show_diverging` could set up (the plugin prints the matching legend).
SCALE_RED_IN = "red-white-blue"
SCALE_BLUE_IN = "blue-white-red"
SCALE_DEFAULT = "default"


def color_scale_xml(
    *, name: str = SCALE_NAME, uuid: str = SCALE_UUID, limit: float | None = None
) -> str:
    """CloudCompare colour-scale XML: Red > White > Blue.

    Red at the low end (negative deformation: the surface moved into the tunnel), white in the
    middle, blue at the high end (outward). Without ``limit`` the scale is *relative*, so that
    CloudCompare's symmetrical-scale and saturation settings centre it on 0 (the plugin); with
    ``limit`` (m) it is *absolute* from ``-limit`` to ``+limit`` (the command line's
    ``-SF_COLOR_SCALE``, which has no saturation option).
    """
    if limit is None:
        props = "<absolute>0</absolute>"
    else:
        props = (
            f"<absolute>1</absolute>\n            <minValue>{-limit:.9g}</minValue>\n"
            f"            <range>{2 * limit:.9g}</range>"
        )
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<CloudCompare>
    <ColorScale version="1">
        <Properties>
            <name>{name}</name>
            <uuid>{uuid}</uuid>
            {props}
        </Properties>
        <Data>
            <step r="255" g="0" b="0" pos="0"/>
            <step r="255" g="255" b="255" pos="0.5"/>
            <step r="0" g="0" b="255" pos="1"/>
        </Data>
    </ColorScale>
</CloudCompare>
"""


def red_white_blue_scale() -> Any:
    """The plugin's Red>White>Blue colour scale, or None if this runtime cannot build one.

    The runtime binds ``ccColorScale.Shared`` (what ``ccScalarField.setColorScale`` takes) as
    an opaque type: a scale built step by step in Python cannot be handed to a scalar field,
    but ``ccColorScale.LoadFromXML`` returns one. The XML (:func:`color_scale_xml`) is written
    to a temporary file and loaded; the scale is also registered with
    ``ccColorScalesManager.GetUniqueInstance().addScale`` (same UUID every time, so a re-run
    replaces it) so that it is listed in the scalar field's properties.
    """
    pycc = pycc_module()
    load = getattr(getattr(pycc, "ccColorScale", None), "LoadFromXML", None)
    if load is None:
        log.info("this runtime has no ccColorScale.LoadFromXML; using the built-in scale")
        return None
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "tunneldef_deformation_scale.xml")
            with open(path, "w", encoding="utf-8") as fh:
                fh.write(color_scale_xml())
            scale = load(path)
    except Exception as exc:  # noqa: BLE001 - any runtime failure: fall back to built-in
        log.warning("could not build the Red>White>Blue scale (%s); using the built-in one", exc)
        return None
    if scale is None:
        return None
    manager = getattr(pycc, "ccColorScalesManager", None)
    if manager is not None and hasattr(manager, "GetUniqueInstance"):
        try:
            try_call(manager.GetUniqueInstance(), "addScale", scale)
        except Exception as exc:  # noqa: BLE001 - listing the scale is a convenience only
            log.debug("addScale failed: %s", exc)
    return scale


def show_diverging(entity: Any, name: str, *, limit: float, scale: Any = None) -> str:
    """Display scalar field ``name`` on a diverging scale centred on 0.

    With ``scale`` (from :func:`red_white_blue_scale`): negative values (surface moved into
    the tunnel) red, white at 0, positive blue, the project's convention. Without it,
    CloudCompare's built-in Blue>White>Red scale (colours the other way round). Either way
    ``setSymmetricalScale(True)`` and saturation 0..``limit`` on |value|, so colours saturate
    at ``±limit`` metres. The display range is left at the field's min..max: CloudCompare
    hides values outside it, and the largest changes must stay visible. Each call is skipped
    if the runtime lacks it.

    Returns
    -------
    str
        ``"red-white-blue"`` (``scale`` set), ``"blue-white-red"`` (built-in scale set) or
        ``"default"`` (no scale could be set; CloudCompare's default scale shows).
    """
    pycc = pycc_module()
    idx = sf_index(entity, name)
    if idx < 0:
        raise ValueError(f"the cloud has no scalar field {name!r}")
    entity.setCurrentDisplayedScalarField(idx)
    sf = entity.getScalarField(idx)
    sf.computeMinAndMax()
    shown = SCALE_DEFAULT
    if scale is not None and try_call(sf, "setColorScale", scale):
        shown = SCALE_RED_IN
    else:
        manager = getattr(pycc, "ccColorScalesManager", None)
        if manager is not None and hasattr(manager, "BWR"):
            if try_call(sf, "setColorScale", manager.GetDefaultScale(manager.BWR)):
                shown = SCALE_BLUE_IN
    try_call(sf, "setSymmetricalScale", True)
    try_call(sf, "setSaturationStart", 0.0)
    try_call(sf, "setSaturationStop", float(limit))
    entity.showSF(True)
    try_call(entity, "showSFColorsScale", True)
    return shown

