"""Progress reporting without any host: stages call a callback, hosts decide how to show it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["ProgressCallback", "Cancelled", "report", "timed_stage"]

#: ``callback(stage, fraction)``: ``stage`` is a short human label, ``fraction`` in [0, 1].
#: A callback may raise :class:`Cancelled` to stop the computation.
ProgressCallback = Callable[[str, float], None]


class Cancelled(Exception):
    """Raised by a progress callback to cancel a running computation."""


def report(callback: ProgressCallback | None, stage: str, fraction: float) -> None:
    """Call ``callback`` if there is one (a no-op otherwise)."""
    if callback is not None:
        callback(stage, min(max(float(fraction), 0.0), 1.0))


@contextmanager
def timed_stage(logger: logging.Logger, message: str) -> Iterator[None]:
    """Log ``message...`` at the start and ``message: done in X s`` at the end (INFO)."""
    start = time.perf_counter()
    logger.info("%s...", message)
    yield
    logger.info("%s: done in %.1f s", message, time.perf_counter() - start)
