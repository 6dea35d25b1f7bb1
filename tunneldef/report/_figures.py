"""Figures without pyplot: no global backend switch, no pyplot state in a host's process."""

from __future__ import annotations

from typing import Any


class FigureFactory:
    """The two pyplot calls the report uses (``subplots``, ``close``), on bare Figures.

    A host such as CloudCompare keeps its own matplotlib backend: nothing here calls
    ``matplotlib.use``. ``Figure.savefig`` picks the writer from the file's extension.
    """

    @staticmethod
    def subplots(*grid: int, figsize: tuple[float, float] | None = None,
                 constrained_layout: bool = False, **kwargs: Any) -> tuple[Any, Any]:
        """A new figure and its axes, as ``pyplot.subplots``."""
        from matplotlib.figure import Figure

        fig = Figure(figsize=figsize, layout="constrained" if constrained_layout else None)
        return fig, fig.subplots(*grid, **kwargs)

    @staticmethod
    def close(fig: Any) -> None:
        """Nothing to release: a bare Figure is garbage-collected like any object."""


def figures() -> FigureFactory:
    """The factory the plotting functions take where they once took ``pyplot``."""
    return FigureFactory()
