"""Exceptions raised by tunneldef.

Every user-facing problem is a :class:`TunnelDefError` with a one-line message that names the
problem and, where possible, the fix. Hosts (the CLI, the CloudCompare plugin) print the message
and exit with code 2 instead of showing a traceback.
"""

from __future__ import annotations

__all__ = [
    "TunnelDefError",
    "UnsupportedFormatError",
    "CorruptFileError",
    "InvalidCloudError",
    "NotATunnelError",
    "RegistrationError",
    "EpochMismatchError",
    "ConfigError",
    "MissingFileError",
    "ImplausibleExtentError",
    "NetworkError",
]


class TunnelDefError(Exception):
    """Root of all tunneldef errors (a user-facing, one-line problem)."""


class UnsupportedFormatError(TunnelDefError):
    """The file extension or format variant is not supported."""


class CorruptFileError(TunnelDefError):
    """A file exists but cannot be parsed."""


class InvalidCloudError(TunnelDefError):
    """A point cloud is empty, badly shaped, or has non-finite coordinates."""


class NotATunnelError(TunnelDefError):
    """The cloud does not look like an elongated tunnel (no usable axis or sections)."""


class RegistrationError(TunnelDefError):
    """Two epochs cannot be registered (too little overlap, no common axis)."""


class EpochMismatchError(TunnelDefError):
    """Two epochs are incompatible (different units, no overlap, same file twice)."""


class ConfigError(TunnelDefError):
    """A configuration value or file is invalid."""


class MissingFileError(TunnelDefError):
    """An input file does not exist or is not a regular file."""


class ImplausibleExtentError(NotATunnelError):
    """A length or extent is absurd against the data (e.g. a centreline far longer than the
    slice centres it was fitted to), usually because of stray points or a bad unit."""


class NetworkError(NotATunnelError):
    """A drift network whose centrelines the method cannot vouch for (drifts above one
    another, an extent too large for the plan grid, a branch without tunnel sections)."""
