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

__all__ = ["Cloud", "Config", "TunnelDefError", "load_config", "read", "write", "__version__"]

logging.getLogger(__name__).addHandler(logging.NullHandler())


def read(path, **kwargs):  # noqa: ANN001, ANN201 - thin re-export, see tunneldef.io.read
    """Read a point cloud file (PLY, LAS, LAZ, PCD, XYZ/TXT); see :func:`tunneldef.io.read`."""
    from .io import read as _read

    return _read(path, **kwargs)


def write(path, cloud, **kwargs):  # noqa: ANN001, ANN201 - thin re-export
    """Write a point cloud file atomically; see :func:`tunneldef.io.write`."""
    from .io import write as _write

    return _write(path, cloud, **kwargs)
