"""Deformation in chainage tiles: memory bounded by a tile, the same values as in one piece.

Once both epochs are registered, :func:`tiled_deformation` cuts them along the reference
centreline into tiles of ``tile_length`` metres, each widened by a margin on both sides, writes
every tile's points into a folder (``.npy`` files: the tasks get paths, never arrays) and runs
the deformation of each tile as a Dask task (:mod:`.engine`). A tile measures all the points it
holds and keeps the values of the compared points it owns (chainage in its own interval); the
margins hold everything the deformation of an owned point depends on.

What makes a tile's values equal to the untiled ones
----------------------------------------------------
Local inputs need the margin (:func:`tile_margin`): the 1 m chainage windows of the shell
envelope, the voxel of a core, the normals' and the cylinders' neighbourhoods (the wide
cylinder included), the cores a point is assigned to and interpolated from, the pooling
and sharpening neighbourhoods of those cores, and the planar cores within 1 m that judge a
core next to an edge (covered by the same 1 m term as the shell windows). Inputs taken from
the whole clouds are computed once, from the whole clouds, and handed to every tile:

* the local origin (the reference's mean) and the corner of the core voxel grid (the compared
  epoch's minimum), by the driver from the coordinates;
* the chainage range the reference covers (0.05-99.95 % quantiles of a fixed subsample);
* the corner of the normals' voxel grid (the minimum of the reference's shell points and of the
  cores): a first pass over the tiles (``survey``), each reporting the minimum over what it owns;
* the typical cylinder spreads (the medians over all cores of both epochs' spreads): a second
  pass (``spreads``), each tile writing the spreads of the cores it owns (a core belongs to the
  tile that owns its first point);
* the surface labels (section extents per 1 m bin, with the whole cloud's as fallback), the
  danger classification and the sections, by the driver on the merged per-point fields.

The test for changes that one epoch shows both surfaces of looks within about 0.4 m of a
point, inside the same 1 m term. One idea at this length: cutting, running and merging the
tiles share the margin and the whole-cloud inputs above, and one is wrong without the others.
"""

from __future__ import annotations

import logging
import math
import os
import pickle
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .config import DeformationConfig
from .curve import Centerline
from .deformation.result import DeformationResult
from .deformation.sections import surface_labels
from .engine import Engine
from .errors import ConfigError
from .progress import ProgressCallback, notify, under

__all__ = ["tile_margin", "tile_length_for", "tiled_deformation", "project_chunked",
           "BYTES_PER_POINT"]

logger = logging.getLogger(__name__)

#: Peak memory of the deformation stage per compared point (with its reference point), bytes;
#: measured on the 350 m pair: a tile of 2.5 M + 2.5 M points (margins included) took the
#: process from 1.9 to 4.0 GB.
BYTES_PER_POINT = 850
_CHUNK = 2_000_000  # points projected at once
_MIN_TILE = 10.0  # m


def tile_margin(settings: DeformationConfig) -> float:
    """Margin added on both sides of a tile, metres, so that every owned point's value is the
    untiled one.

    ``robust``: the longer of two chains of what an owned point's value depends on, times 1.2
    for curves (chainage shrinks inside a bend):

    * the surfaces: its core (within ``normal_radius + 2 core_spacing``), the cores
      interpolated at it (1.5 spacings), the sharpening (1.5 spacings) and pooling (3 sigma of
      the coarser pooled mean) of those cores, their wide cylinders (``hypot(2
      cylinder_radius, max_depth)``) and the normals and shell windows (1 m) of the points in
      them;
    * the stand-off test of a point the shell classifier left out: its core, the shell windows
      that decide which points make that core (1 m), and the rays behind the core (up to twice
      ``standoff_reach``, as thick as the probe). The test reads the points on the rays
      whatever their class, and decides that point's value alone, so this chain does not add
      to the first.

    ``knn``: three times ``max_distance``. Never less than 3 m.
    """
    s, r, nr = settings.core_spacing, settings.cylinder_radius, settings.normal_radius
    if settings.method == "knn":
        return max(3.0, 3.0 * float(settings.max_distance))
    s2 = math.sqrt(2.0 * r**2 + 0.25 * r**2 + (0.6 * s) ** 2)
    surfaces = ((nr + 2 * s) + 1.5 * s + 1.5 * s + 3.0 * s2
                + 2.0 * math.hypot(2 * r, settings.max_depth) + (nr + s) + math.sqrt(3) * s
                + 1.0)
    from .deformation.compute import _PROBE_RADIUS

    standoff = (nr + 2 * s) + 1.0 + 2.0 * settings.standoff_reach + 2.0 * _PROBE_RADIUS
    return max(3.0, 1.2 * max(surfaces, standoff))


def tile_length_for(points_per_metre: float, memory_gb: float, margin: float) -> float:
    """Tile length (m) whose points, margins included, fit ``memory_gb`` of working memory."""
    budget = memory_gb * 1e9 / BYTES_PER_POINT / max(points_per_metre, 1.0)
    return float(max(_MIN_TILE, budget - 2.0 * margin))


def project_chunked(
    centerline: Centerline, xyz: np.ndarray, *, full: bool = False
) -> tuple[np.ndarray, ...]:
    """Chainage of points (and with ``full``, lateral, vertical offsets and ``inside``),
    projected a chunk at a time (the projection is point by point: the values are those of one
    call)."""
    n = len(xyz)
    s = np.empty(n)
    lat = np.empty(n) if full else None
    ver = np.empty(n) if full else None
    inside = np.empty(n, dtype=bool) if full else None
    for a in range(0, n, _CHUNK):
        p = centerline.project(xyz[a:a + _CHUNK])
        s[a:a + _CHUNK] = p.chainage
        if full:
            lat[a:a + _CHUNK], ver[a:a + _CHUNK] = p.lateral, p.vertical
            inside[a:a + _CHUNK] = p.inside
    return (s, lat, ver, inside) if full else (s,)


@dataclass(frozen=True)
class _Tile:
    folder: str
    owned: int


def _edges(lo: float, hi: float, tile_length: float) -> np.ndarray:
    n = max(1, int(math.ceil((hi - lo) / tile_length - 1e-9)))
    return np.r_[-np.inf, lo + (hi - lo) * np.arange(1, n) / n, np.inf]


def _cut(
    workdir: Path, ref: np.ndarray, cmp: np.ndarray, ref_s: np.ndarray, cmp_s: np.ndarray,
    edges: np.ndarray, margin: float,
) -> list[_Tile]:
    """Write each tile's points (in file order) to ``workdir/tile_XXXX``.

    Each tile's points are found by a pass over the chainages (no sorted copies of the
    whole clouds: memory beyond the clouds stays that of one tile)."""
    tiles = []
    for i in range(len(edges) - 1):
        a, b = edges[i], edges[i + 1]
        folder = workdir / f"tile_{i:04d}"
        folder.mkdir()
        ri = np.flatnonzero((ref_s >= a - margin) & (ref_s < b + margin))
        ci = np.flatnonzero((cmp_s >= a - margin) & (cmp_s < b + margin))
        owned = (cmp_s[ci] >= a) & (cmp_s[ci] < b)
        np.save(folder / "ref.npy", ref[ri])
        np.save(folder / "cmp.npy", cmp[ci])
        np.save(folder / "cmp_index.npy", ci)
        np.save(folder / "cmp_owned.npy", owned)
        tiles.append(_Tile(str(folder), int(owned.sum())))
    return tiles


def _load(folder: str, *names: str) -> list[np.ndarray]:
    return [np.load(os.path.join(folder, f"{n}.npy")) for n in names]


def _save(folder: str, name: str, a: Any) -> None:
    """Write atomically (a task run again after a lost worker rewrites the same file): an
    array as ``name.npy``, or an object with a ``save(path)`` method as ``name.npz``."""
    ext = "npy" if isinstance(a, np.ndarray) else "npz"
    tmp = os.path.join(folder, f".{name}.{os.getpid()}.tmp.{ext}")
    if ext == "npy":
        np.save(tmp, a)
    else:
        a.save(tmp)
    os.replace(tmp, os.path.join(folder, f"{name}.{ext}"))


def _context(workdir: str) -> tuple[Centerline, DeformationConfig]:
    with open(os.path.join(workdir, "context.pkl"), "rb") as f:
        return pickle.load(f)


def _robust_inputs(centerline, settings, ref, cmp, inputs):
    from .deformation.compute import _robust_kwargs

    return dict(_robust_kwargs(settings), **inputs)


def _survey_task(workdir: str, folder: str) -> int:
    """Pass 1: both epochs' shell masks cut at one level, and the compared epoch's own shell
    mask (the points the estimator's first pass measures), saved."""
    from .deformation import shell as shell_module
    from .deformation.compute import _envelope, common_masks

    centerline, _ = _context(workdir)
    ref, cmp = _load(folder, "ref", "cmp")
    ref_pp, r_env, r_off, r_obl = _envelope(ref, centerline, -1)
    cmp_pp, c_env, c_off, c_obl = _envelope(cmp, centerline, -1)
    ref_mask, cmp_mask = common_masks(r_env, ref_pp, r_off, r_obl, c_env, cmp_pp, c_off, c_obl)
    _save(folder, "ref_mask", ref_mask)
    _save(folder, "cmp_mask", cmp_mask)
    _save(folder, "cmp_shell", shell_module.shell_mask(c_off, c_obl))
    return len(cmp)


def _spreads_task(workdir: str, folder: str, inputs: dict[str, Any]) -> int:
    """Pass 2: cylinder spreads of the cores this tile owns (saved), and the estimator's state
    after them, which pass 3 resumes from."""
    from .deformation.local_surface import robust_deformation

    centerline, settings = _context(workdir)
    ref, cmp, ref_mask, cmp_mask, cmp_shell, cmp_owned = _load(
        folder, "ref", "cmp", "ref_mask", "cmp_mask", "cmp_shell", "cmp_owned")
    if not cmp_shell.any():  # nothing on the shell here: no cylinders, nothing to resume
        for name in ("spread_ref", "spread_cmp"):
            _save(folder, name, np.empty(0))
        return 0
    state = robust_deformation(
        ref, cmp, centerline, ref_mask=ref_mask, cmp_mask=cmp_mask, measure=cmp_shell,
        spreads_only=True, **_robust_inputs(centerline, settings, ref, cmp, inputs))
    first = np.unique(state.inverse, return_index=True)[1]  # points are in file order
    mine = cmp_owned[cmp_shell][first]
    _save(folder, "spread_ref", state.spread_ref[mine])
    _save(folder, "spread_cmp", state.spread_cmp[mine])
    _save(folder, "cylinders", state)
    return int(mine.sum())


def _measure_task(
    workdir: str, folder: str, coverage: tuple[float, float], inputs: dict[str, Any] | None,
    registration_sigma: float = 0.0,
) -> str:
    """Pass 3: the deformation of the tile; the owned points' fields are saved."""
    from .deformation.compute import compute_deformation

    centerline, settings = _context(workdir)
    ref, cmp, cmp_owned = _load(folder, "ref", "cmp", "cmp_owned")
    reuse: dict[str, Any] = {}
    if inputs is not None and os.path.exists(os.path.join(folder, "cmp_shell.npy")):
        # the survey pass's shell masks (the same functions on the same points)
        ref_mask, cmp_mask, cmp_shell = _load(folder, "ref_mask", "cmp_mask", "cmp_shell")
        reuse = {"shell": cmp_shell, "masks": (ref_mask, cmp_mask)}
        state = os.path.join(folder, "cylinders.npz")
        if os.path.exists(state):  # and the spreads pass's cylinders, on the same points
            from .deformation.local_surface import CylinderPass

            reuse["resume"] = CylinderPass.load(state)
    d = compute_deformation(ref, cmp, centerline, settings=settings, coverage=coverage,
                            robust_inputs=inputs, registration_sigma=registration_sigma,
                            **reuse)
    fields = {"deformation": d.deformation, "horizontal": d.horizontal,
              "vertical": d.vertical, "shell": d.shell}
    if d.significant is not None:
        fields["significant"] = d.significant
    if d.lod95 is not None:
        fields["lod95"] = d.lod95
    if d.two_surfaces is not None:
        fields["two_surfaces"] = d.two_surfaces
    if d.spread_ratio is not None:
        fields["spread_ratio"] = d.spread_ratio
    for name, a in fields.items():
        _save(folder, f"out_{name}", np.asarray(a)[cmp_owned])
    return folder


def tiled_deformation(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    centerline: Centerline,
    *,
    settings: DeformationConfig | None = None,
    tile_length: float | None = None,
    memory_gb: float = 1.5,
    engine: Engine | None = None,
    workdir: str | os.PathLike[str] | None = None,
    chainage: np.ndarray | None = None,
    surface: np.ndarray | None = None,
    registration_sigma: float = 0.0,
    progress: ProgressCallback | None = None,
) -> DeformationResult:
    """:func:`tunneldef.deformation.compute_deformation` run tile by tile as Dask tasks.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (M, 3), (N, 3)
        Reference epoch and the compared epoch registered into its frame, metres.
    centerline : Centerline
        The reference centreline.
    settings : DeformationConfig, optional
        ``[deformation]`` parameters.
    tile_length : float, optional
        Owned length of a tile along the chainage, metres; by default from ``memory_gb``.
    memory_gb : float
        Working memory one tile may take, GB (chooses ``tile_length`` when it is not given).
    engine : Engine, optional
        Where the tasks run (default: Dask's local threaded scheduler, one tile at a time).
    workdir : path, optional
        Folder for the tiles' files, readable by every worker; a temporary folder (removed
        afterwards) is made inside it.
    chainage, surface : ndarray, shape (N,), optional
        The compared points' chainage on ``centerline`` and their surface labels
        (:func:`tunneldef.deformation.sections.surface_labels`), when the caller has them (both
        or neither; a caller that drops the lateral and vertical offsets once it has the labels
        keeps them out of memory while the tiles run).
    registration_sigma : float
        Standard uncertainty of the registration, metres (see ``compute_deformation``).
    progress : callable, optional
        ``progress(stage, fraction)``.

    Returns
    -------
    DeformationResult
        The same values as the untiled stage (within float rounding, < 1e-6 m). When the
        survey is cut into more than one tile, the merged ``deformation``, ``horizontal``,
        ``vertical`` and ``lod95`` are float32 (the precision they are written in: under
        1e-7 m below 1 m), which keeps half their memory on large surveys.
    """
    settings = settings or DeformationConfig()
    engine = engine or Engine(None, 1)
    margin = tile_margin(settings)
    notify(progress, "tiles", 0.0)
    ref_s = project_chunked(centerline, ref_xyz)[0]
    if (chainage is None) != (surface is None):
        raise ValueError("give both the chainage and the surface labels, or neither")
    from .deformation.compute import _coverage

    coverage = _coverage(ref_xyz, centerline, -1, ref_s)
    if tile_length is None:
        tile_length = tile_length_for(len(cmp_xyz) / max(coverage[1] - coverage[0], 1.0),
                                      memory_gb, margin)
    if not tile_length > 0:
        raise ConfigError(f"tile length must be > 0 m, got {tile_length!r}")
    edges = _edges(coverage[0], coverage[1], tile_length)
    if len(edges) == 2:  # one tile holds both clouds whole: nothing to cut, nothing to pass on
        from .deformation.compute import compute_deformation

        notify(progress, "tiles", 1.0)
        logger.info("one tile: the survey fits %.1f m", tile_length)
        return compute_deformation(ref_xyz, cmp_xyz, centerline, settings=settings,
                                   coverage=coverage, registration_sigma=registration_sigma,
                                   progress=under(progress, "deformation"))
    if chainage is None:  # (not needed when one tile holds the survey)
        chainage, lat, ver, _ = project_chunked(centerline, cmp_xyz, full=True)
        surface = surface_labels(chainage, lat, ver, step=settings.section_step)
        del lat, ver
    cmp_s = chainage
    base = Path(workdir) if workdir is not None else None
    tmp = Path(tempfile.mkdtemp(prefix="tunneldef-tiles-", dir=base))
    try:
        with open(tmp / "context.pkl", "wb") as f:
            pickle.dump((centerline, settings), f)
        tiles = [t for t in _cut(tmp, ref_xyz, cmp_xyz, ref_s, cmp_s, edges, margin)
                 if t.owned > 0]
        del ref_s
        logger.info("%d tiles of %.1f m (+ %.1f m margins) in %s", len(tiles), tile_length,
                    margin, tmp)
        notify(progress, "tiles", 1.0)
        inputs: dict[str, Any] | None = None
        if settings.method == "robust":
            from .deformation.compute import global_inputs

            engine.map(_survey_task, [(str(tmp), t.folder) for t in tiles],
                       stage="tiles: shell", progress=progress)
            inputs = global_inputs(ref_xyz, cmp_xyz, settings)
            engine.map(_spreads_task, [(str(tmp), t.folder, inputs) for t in tiles],
                       stage="tiles: cylinders", progress=progress)
            typical = []
            for name in ("spread_ref", "spread_cmp"):
                v = np.concatenate([_load(t.folder, name)[0] for t in tiles])
                typical.append(float(np.nanmedian(v)) if np.isfinite(v).any() else np.inf)
            inputs["typical_spread"] = (typical[0], typical[1])
        engine.map(_measure_task,
                   [(str(tmp), t.folder, coverage, inputs, registration_sigma) for t in tiles],
                   stage="tiles: deformation", progress=progress)
        return _merge(tiles, cmp_xyz, cmp_s, surface, centerline, settings,
                      None if inputs is None else inputs.get("typical_spread"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _merge(tiles, cmp_xyz, cmp_s, surface, centerline, settings,
           typical_spread=None) -> DeformationResult:
    """The owned points' fields of every tile, in the compared epoch's order (float fields as
    float32, the float16 spread ratio as it is)."""
    n = len(cmp_xyz)
    names = ["deformation", "horizontal", "vertical", "shell"]
    if settings.method == "robust":
        names += ["significant", "lod95", "two_surfaces", "spread_ratio"]
    out: dict[str, np.ndarray] = {}
    seen = np.zeros(n, dtype=bool)
    for t in tiles:
        index, owned = _load(t.folder, "cmp_index", "cmp_owned")
        index = index[owned]
        seen[index] = True
        for name in names:
            a = _load(t.folder, f"out_{name}")[0]
            if name not in out:
                kind = np.float32 if a.dtype.kind == "f" and a.dtype.itemsize > 2 else a.dtype
                out[name] = np.empty(n, dtype=kind)
            out[name][index] = a
    if not seen.all():  # every point lies in exactly one owned interval
        raise RuntimeError(f"{int((~seen).sum())} compared points in no tile")
    return DeformationResult(
        deformation=out["deformation"], horizontal=out["horizontal"], vertical=out["vertical"],
        chainage=cmp_s, surface=surface, shell=out["shell"], xyz=cmp_xyz,
        method=settings.method, k=settings.k if settings.method == "knn" else None,
        significant=out.get("significant"), lod95=out.get("lod95"),
        centerline_length=centerline.length, two_surfaces=out.get("two_surfaces"),
        spread_ratio=out.get("spread_ratio"), typical_spread=typical_spread,
    )
