"""tunneldef inside CloudCompare (Python runtime plugin).

``plugin``  : :class:`~tunneldef_cloudcompare.plugin.TunnelDefPlugin`, the menu actions
              (needs ``pycc``, i.e. CloudCompare's embedded Python).
``adapter`` : entities <-> numpy / :class:`tunneldef.Cloud`, global shift/scale, scalar-field
              writing and display; no algorithm code.
``dialog``  : the parameter dialog (Qt imported lazily; plain defaults without Qt).

Importing this package imports neither ``pycc`` nor Qt, so the adapter can be tested anywhere.
"""

from __future__ import annotations

__all__ = ["adapter", "dialog", "plugin"]
