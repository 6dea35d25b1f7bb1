"""tunneldef inside CloudCompare (Python runtime plugin).

``plugin``  : :class:`~tunneldef_cloudcompare.plugin.TunnelDefPlugin`, the menu actions
              (needs ``pycc``, i.e. CloudCompare's embedded Python).
``adapter`` : one import for the modules below (entities <-> numpy / :class:`tunneldef.Cloud`;
              no algorithm code): ``params``, ``coords``, ``reading``, ``fields``,
              ``colours``, ``entities``, ``runtime``, ``worker``, ``jobs``, ``text``.
``dialog``  : the parameter dialog (Qt imported lazily; plain defaults without Qt).

Importing this package imports neither ``pycc`` nor Qt, so the adapter can be tested anywhere.
"""

from __future__ import annotations

__all__ = [
    "adapter",
    "colours",
    "coords",
    "dialog",
    "entities",
    "fields",
    "jobs",
    "params",
    "plugin",
    "reading",
    "runtime",
    "text",
    "worker",
]
