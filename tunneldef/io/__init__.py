"""Point-cloud files in and out: PLY, LAS/LAZ, PCD and XYZ/TXT/ASC/CSV.

``read(path)`` returns a :class:`~tunneldef.cloud.Cloud` with every attribute of the file as a
field; ``write(path, cloud)`` writes one atomically, reusing the source layout when the cloud was
read from the same format family. One module per family: ``las``, ``ply``, ``pcd``, ``xyz``.
"""

from __future__ import annotations

from .core import read, supported_extensions, write

__all__ = ["read", "write", "supported_extensions"]
