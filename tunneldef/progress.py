"""Progress reporting without any host: stages call a callback, hosts decide how to show it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = [
    "ProgressCallback",
    "Cancelled",
    "notify",
    "under",
    "scaled",
    "StageLogger",
    "timed_stage",
]

#: ``callback(stage, fraction)``: ``stage`` is a short human label, ``fraction`` in [0, 1].
#: A callback may raise :class:`Cancelled` to stop the computation.
ProgressCallback = Callable[[str, float], None]


class Cancelled(Exception):
    """Raised by a progress callback to cancel a running computation."""


def notify(callback: ProgressCallback | None, stage: str, fraction: float) -> None:
    """Call ``callback`` if there is one (a no-op otherwise)."""
    if callback is not None:
        callback(stage, min(max(float(fraction), 0.0), 1.0))


def under(callback: ProgressCallback | None, name: str) -> ProgressCallback | None:
    """A callback that reports a stage's sub-steps under the stage's label ``name``."""
    if callback is None:
        return None

    def cb(step: str, fraction: float) -> None:
        same = not step or step.lower() == name.split()[-1].lower()
        callback(name if same else f"{name}: {step}", fraction)

    return cb


def scaled(callback: ProgressCallback | None, lo: float, hi: float) -> ProgressCallback | None:
    """A callback that maps a sub-step's fraction [0, 1] onto [lo, hi] of the caller's."""
    if callback is None:
        return None
    return lambda stage, f: callback(stage, lo + (hi - lo) * f)


class StageLogger:
    """A progress callback that logs one line per stage (and per 25 % inside long stages)."""

    def __init__(self, logger: logging.Logger) -> None:
        self._log = logger
        self._stage: str | None = None
        self._quarter = -1
        self._start = time.perf_counter()

    def __call__(self, stage: str, fraction: float) -> None:
        quarter = int(fraction * 4)
        if stage != self._stage:
            self._stage, self._quarter = stage, quarter
            self._log.info("[%5.1f s] %s", time.perf_counter() - self._start, stage)
        elif quarter > self._quarter and 0 < quarter < 4:
            self._quarter = quarter
            self._log.info("[%5.1f s] %s: %d %%", time.perf_counter() - self._start, stage,
                           quarter * 25)


@contextmanager
def timed_stage(logger: logging.Logger, message: str) -> Iterator[None]:
    """Log ``message...`` at the start and ``message: done in X s`` at the end (INFO)."""
    start = time.perf_counter()
    logger.info("%s...", message)
    yield
    logger.info("%s: done in %.1f s", message, time.perf_counter() - start)
