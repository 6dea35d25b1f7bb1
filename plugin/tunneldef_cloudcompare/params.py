"""Parameters of the "Detect deformation" action and their mapping onto the core's Config."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

__all__ = ["NETWORK_CHOICES", "DetectParams", "config_from_params"]

#: How a pair is treated: ``auto`` (a drift network if either epoch's plan shows junctions),
#: ``single`` (one drift; the core refuses a network) or ``network``.
NETWORK_CHOICES = ("auto", "single", "network")


def _config_default(section: str, name: str) -> Any:
    """A default of :class:`tunneldef.config.Config` (imported only when needed)."""
    from tunneldef.config import Config

    return getattr(getattr(Config(), section), name)


@dataclass(frozen=True)
class DetectParams:
    """What the "Detect deformation" dialog asks.

    Attributes
    ----------
    swap : bool
        False: the first selected cloud is the reference (earlier epoch), the second the
        compared one; True: the other way round.
    threshold : float
        Danger threshold on |deformation|, metres (``Config.danger.threshold``).
    k : int
        Nearest neighbours of the ``knn`` estimator only (``Config.deformation.k``, paper
        §4.3); ``robust`` ignores it.
    method : str
        Deformation estimator, ``"robust"`` (local surface, per-point level of detection) or
        ``"knn"`` (the paper's KNN centroid).
    move_original : bool
        Also move the original compared cloud into the reference frame (default: leave it).
    network : str
        ``"auto"``: a drift network (one centreline per edge, deformation per branch) if either
        epoch's plan shows junctions; ``"single"``: one drift; ``"network"``.

    Every default is the :class:`tunneldef.config.Config` default.
    """

    swap: bool = False
    threshold: float = field(default_factory=lambda: float(_config_default("danger", "threshold")))
    k: int = field(default_factory=lambda: int(_config_default("deformation", "k")))
    method: str = field(default_factory=lambda: str(_config_default("deformation", "method")))
    move_original: bool = False
    network: str = "auto"

    @classmethod
    def from_config(cls, config: Any = None, **overrides: Any) -> DetectParams:
        """Defaults taken from a :class:`tunneldef.config.Config` (its defaults if None)."""
        if config is None:
            from tunneldef.config import Config

            config = Config()
        base = cls(
            threshold=float(config.danger.threshold),
            k=int(config.deformation.k),
            method=str(config.deformation.method),
        )
        return dataclasses.replace(base, **overrides)


def config_from_params(params: DetectParams, base: Any = None) -> Any:
    """The :class:`tunneldef.config.Config` for a run: ``base`` with the dialog's values."""
    if base is None:
        from tunneldef.config import Config

        base = Config()
    return base.replace(
        danger={"threshold": float(params.threshold)},
        deformation={"k": int(params.k), "method": str(params.method)},
    )

