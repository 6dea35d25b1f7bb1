"""Time of fitting and sampling a NURBS centreline, and of refusing an absurd one.

A 300 m curved axis (R = 150 m, 2 % grade) with a slice centre every 0.5 m and 1 cm noise is
fitted with the defaults (a control point per 2 m, samples every 5 cm). The geomdl column
evaluates the same fitted curve with ``geomdl.NURBS.Curve.evaluate_list`` at the same
parameters, as the fitting used to. The last row puts the last station 1.4e6 m down the axis
(a stray point and an oversized extent), which must be refused at once.

Run: ``python benchmarks/centerline_speed.py``
"""

from __future__ import annotations

import time

import numpy as np

from tunneldef.centerline.fit import fit_centerline
from tunneldef.errors import ImplausibleExtentError


def _centres(length: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    s = np.arange(0.0, length + 1e-9, 0.5)
    th = s / 150.0
    q = np.c_[150.0 * np.sin(th), 150.0 * (1 - np.cos(th)), 0.02 * s]
    return q + rng.normal(0.0, 0.01, q.shape), s


def main() -> None:
    q, s = _centres(300.0)
    fit_centerline(q[:40], params=s[:40])  # warm up imports
    times = []
    for _ in range(5):
        start = time.perf_counter()
        cl, fit = fit_centerline(q, params=s)
        times.append(time.perf_counter() - start)
    n_eval = int(round(cl.length / cl.meta["eval_step_m"])) + 1
    u = np.linspace(0.0, 1.0, n_eval)
    start = time.perf_counter()
    fit.curve.evaluate_list(u.tolist())
    t_geomdl = time.perf_counter() - start
    start = time.perf_counter()
    fit.evaluate(u)
    t_scipy = time.perf_counter() - start
    print("| case | time |")
    print("| --- | --- |")
    print(
        f"| fit + sample 300 m ({len(cl.points)} samples), median of 5 | "
        f"{np.median(times) * 1e3:.1f} ms |"
    )
    print(f"| evaluate {n_eval} points, scipy | {t_scipy * 1e3:.1f} ms |")
    print(f"| evaluate {n_eval} points, geomdl | {t_geomdl * 1e3:.1f} ms |")
    s_bad = s.copy()
    s_bad[-1] = 1.4e6
    start = time.perf_counter()
    try:
        fit_centerline(q, params=s_bad)
        verdict = "accepted (wrong)"
    except ImplausibleExtentError:
        verdict = "ImplausibleExtentError"
    print(f"| last station at 1.4e6 m | {(time.perf_counter() - start) * 1e3:.1f} ms, {verdict} |")


if __name__ == "__main__":
    main()
