"""tunneldef: tunnel deformation from two epochs of mobile laser scans.

The method follows Sensors 2024, 24, 2299 (doi:10.3390/s24072299): PCA axis alignment, slicing,
roof/floor and wall lines from kernel-density peaks and Hough lines, a NURBS centreline,
centreline-based registration of two epochs, and per-point / per-section deformation.
"""

from __future__ import annotations

import logging

from .cloud import Cloud
from .config import Config, load_config
from .errors import TunnelDefError

__version__ = "0.1.0"

__all__ = [
    "Cloud",
    "Config",
    "TunnelDefError",
    "load_config",
    "read",
    "write",
    "detect",
    "extract_centerline",
    "register",
    "compute_deformation",
    "__version__",
]

#: The main verbs, loaded on first use so that ``import tunneldef`` stays light.
_VERBS = {
    "read": ("tunneldef.io", "read"),
    "write": ("tunneldef.io", "write"),
    "detect": ("tunneldef.pipeline", "detect"),
    "extract_centerline": ("tunneldef.centerline", "extract_centerline"),
    "register": ("tunneldef.registration", "register"),
    "compute_deformation": ("tunneldef.deformation", "compute_deformation"),
}

logging.getLogger(__name__).addHandler(logging.NullHandler())


def __getattr__(name: str):  # noqa: ANN202 - module attribute hook (PEP 562)
    if name in _VERBS:
        import importlib

        module, attr = _VERBS[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'tunneldef' has no attribute {name!r}")
