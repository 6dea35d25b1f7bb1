"""CloudCompare entities <-> numpy arrays and :class:`tunneldef.Cloud`; no algorithm code.

One import for everything CloudCompare-specific that the plugin and the scripts share; the
code lives in one module per concern:

* :mod:`.params` - the dialog's parameters and the core's ``Config`` for them;
* :mod:`.coords` - local float32 coordinates, global shift and scale;
* :mod:`.reading` - entities -> float64 survey coordinates, :class:`tunneldef.Cloud`;
* :mod:`.fields` - scalar fields (written replacing same-named ones);
* :mod:`.colours` - the Red > White > Blue scale centred on 0 (red = into the tunnel);
* :mod:`.entities` - new clouds and polylines, moving an entity;
* :mod:`.runtime` - ``pycc`` lookup and the check that the runtime's arrays are sound;
* :mod:`.worker` - the core on a worker thread with the GUI kept alive, progress, Cancel;
* :mod:`.jobs` - the three jobs: compute (worker) and apply (main thread);
* :mod:`.text` - console tables.

Nothing here imports ``pycc`` or Qt at import time: functions that need ``pycc`` take it from
``sys.modules``/import when called, so a stand-in module can be injected in tests.
"""

from __future__ import annotations

from .colours import (
    SCALE_BLUE_IN,
    SCALE_DEFAULT,
    SCALE_NAME,
    SCALE_RED_IN,
    SCALE_UUID,
    color_scale_xml,
    red_white_blue_scale,
    show_diverging,
    symmetric_limit,
)
from .coords import (
    copy_shift_and_scale,
    global_to_local,
    local_to_global,
    local_transform,
    shift_and_scale,
)
from .entities import make_point_cloud, make_polyline, move_entity
from .fields import write_scalar_fields
from .jobs import (
    DEFORMATION_FIELDS,
    NETWORK_CHOICES,
    OPTIONAL_FIELDS,
    DetectEntities,
    apply_centerline,
    apply_detect,
    apply_register,
    compute_centerline,
    compute_detect,
    compute_register,
    is_network,
    result_fields,
)
from .params import DetectParams, config_from_params
from .reading import entity_to_cloud, point_clouds, read_points
from .runtime import BrokenRuntimeError, check_runtime, entity_name
from .text import format_matrix, format_slice_table
from .worker import Outcome, ProgressBridge, run_guarded, run_in_worker

__all__ = [
    "DEFORMATION_FIELDS",
    "NETWORK_CHOICES",
    "is_network",
    "OPTIONAL_FIELDS",
    "DetectParams",
    "Outcome",
    "ProgressBridge",
    "BrokenRuntimeError",
    "check_runtime",
    "entity_name",
    "config_from_params",
    "local_to_global",
    "global_to_local",
    "local_transform",
    "shift_and_scale",
    "copy_shift_and_scale",
    "read_points",
    "entity_to_cloud",
    "point_clouds",
    "write_scalar_fields",
    "symmetric_limit",
    "SCALE_NAME",
    "SCALE_UUID",
    "SCALE_RED_IN",
    "SCALE_BLUE_IN",
    "SCALE_DEFAULT",
    "color_scale_xml",
    "red_white_blue_scale",
    "show_diverging",
    "make_point_cloud",
    "make_polyline",
    "move_entity",
    "run_guarded",
    "run_in_worker",
    "compute_detect",
    "apply_detect",
    "compute_centerline",
    "apply_centerline",
    "compute_register",
    "apply_register",
    "format_matrix",
    "format_slice_table",
    "result_fields",
    "DetectEntities",
]
