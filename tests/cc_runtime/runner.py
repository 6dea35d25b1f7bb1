"""Find, unpack and run the prebuilt CloudCompare 2.13 + PythonRuntime for the tests and the
benchmarks.

The build is looked for, in order: ``$TUNNELDEF_CC_PREFIX``, ``/opt/cloudcompare-python``, and
the tarball in ``../shared/cloudcompare-python/`` beside the repository (unpacked once into
``$TUNNELDEF_CC_CACHE`` or the system's temporary folder). CloudCompare's Python gets the
packages of ``$TUNNELDEF_CC_SITE`` or, when the running interpreter is Python 3.11 like the
runtime, this interpreter's ``site-packages``, after the repository itself (so the code under
test is the working tree's). ``VIRTUAL_ENV`` is removed from the environment: with it the
runtime's interpreter fails to start ("failed to get the Python codec of the filesystem
encoding").
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared" / "cloudcompare-python"
TARBALL = SHARED / "cloudcompare-2.13.1-pythonruntime-qt5-debian12.tar.gz"
HERE = Path(__file__).resolve().parent

__all__ = ["Unavailable", "Runtime", "find_runtime", "harness_path", "write_pair"]


class Unavailable(Exception):
    """The real CloudCompare runtime is not there (the reason says why)."""


@dataclass
class Runtime:
    """A usable CloudCompare + PythonRuntime: executable, libraries and Python packages."""

    prefix: Path
    site: Path

    @property
    def exe(self) -> Path:
        return self.prefix / "bin" / "CloudCompare"

    def env(self, config_dir: Path, extra_path: list[Path] | None = None) -> dict[str, str]:
        """The environment CloudCompare needs (PYTHONPATH, not VIRTUAL_ENV)."""
        env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "CONDA_PREFIX")}
        paths = [*(extra_path or []), REPO, REPO / "plugin", self.site]
        env["PYTHONPATH"] = os.pathsep.join(str(p) for p in paths)
        env["LD_LIBRARY_PATH"] = str(self.prefix / "lib" / "cloudcompare")
        env["XDG_CONFIG_HOME"] = str(config_dir)  # CloudCompare's settings, kept out of ~
        runtime_dir = config_dir / "runtime"
        runtime_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        env["XDG_RUNTIME_DIR"] = str(runtime_dir)
        env.pop("PYTHONHOME", None)
        # the runtime's embedded Python finds its standard library from the first `python3` on
        # PATH: a virtual environment's (or pyenv's) would hide the system's dist-packages,
        # where PySide2 and the runtime's own Python live; keep only system directories
        env["PATH"] = os.pathsep.join(
            d for d in env.get("PATH", "").split(os.pathsep)
            if d and not (Path(d) / "pyvenv.cfg").exists()
            and not (Path(d).parent / "pyvenv.cfg").exists() and ".pyenv" not in d
        ) or "/usr/local/bin:/usr/bin:/bin"
        return env

    def run(
        self,
        args: list[str],
        *,
        workdir: Path,
        gui: bool = False,
        env_extra: dict[str, str] | None = None,
        extra_path: list[Path] | None = None,
        timeout: float = 300,
    ) -> subprocess.CompletedProcess:
        """Run CloudCompare with ``args``: offscreen (``-SILENT`` scripts) or under Xvfb."""
        config = workdir / "config"
        config.mkdir(parents=True, exist_ok=True)
        env = self.env(config, extra_path)
        env.update(env_extra or {})
        if gui:
            cmd = ["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", str(self.exe), *args]
        else:
            env["QT_QPA_PLATFORM"] = "offscreen"
            cmd = [str(self.exe), *args]
        return subprocess.run(
            cmd, cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout
        )

    def run_script(
        self,
        script: Path,
        clouds: list[Path],
        *,
        workdir: Path,
        script_args: list[str] | None = None,
        global_shift: bool = True,
        env_extra: dict[str, str] | None = None,
        timeout: float = 300,
    ) -> subprocess.CompletedProcess:
        """``CloudCompare -SILENT -AUTO_SAVE OFF -O [-GLOBAL_SHIFT AUTO] cloud ...
        -PYTHON_SCRIPT script [args]``."""
        args = ["-SILENT", "-AUTO_SAVE", "OFF"]
        for c in clouds:
            args += ["-O", *(["-GLOBAL_SHIFT", "AUTO"] if global_shift else []), str(c)]
        args += ["-PYTHON_SCRIPT", str(script), *(script_args or [])]
        return self.run(args, workdir=workdir, env_extra=env_extra, timeout=timeout)

    def run_gui(
        self,
        clouds: list[Path],
        *,
        workdir: Path,
        env_extra: dict[str, str] | None = None,
        timeout: float = 300,
    ) -> subprocess.CompletedProcess:
        """CloudCompare's window under Xvfb with ``clouds`` loaded, driven by ``gui_harness``
        (results in ``$TDCC_OUT``, default ``workdir``)."""
        env = {
            "TDCC_GUI": "1",
            "TDCC_OUT": str(workdir),
            "TDCC_CLOUDS": os.pathsep.join(str(c) for c in clouds),
            **(env_extra or {}),
        }
        return self.run(
            [],
            workdir=workdir,
            gui=True,
            env_extra=env,
            extra_path=harness_path(workdir),
            timeout=timeout,
        )


def harness_path(workdir: Path) -> list[Path]:
    """``PYTHONPATH`` entries that make the runtime import ``gui_harness`` at start-up: a
    ``.dist-info`` declaring it under the ``cloudcompare.plugins`` entry point, and its folder."""
    site = workdir / "harness_site"
    info = site / "tdcc_harness-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: tdcc-harness\nVersion: 0.0\n", encoding="utf-8"
    )
    (info / "entry_points.txt").write_text(
        "[cloudcompare.plugins]\ntdcc_harness = gui_harness:HarnessPlugin\n", encoding="utf-8"
    )
    return [site, HERE]


def _site_packages() -> Path:
    explicit = os.environ.get("TUNNELDEF_CC_SITE")
    if explicit:
        return Path(explicit)
    if sys.version_info[:2] != (3, 11):
        raise Unavailable(
            "CloudCompare's runtime is Python 3.11 and this interpreter is "
            f"{sys.version_info[0]}.{sys.version_info[1]}: set TUNNELDEF_CC_SITE to the "
            "site-packages of a Python 3.11 environment with tunneldef's dependencies"
        )
    return Path(sysconfig.get_paths()["purelib"])


def _prefix() -> Path:
    for cand in (os.environ.get("TUNNELDEF_CC_PREFIX"), "/opt/cloudcompare-python"):
        if cand and (Path(cand) / "bin" / "CloudCompare").is_file():
            return Path(cand)
    if not TARBALL.is_file():
        raise Unavailable(
            f"CloudCompare 2.13 + PythonRuntime not available: {TARBALL} is absent (and no "
            "TUNNELDEF_CC_PREFIX or /opt/cloudcompare-python)"
        )
    cache = Path(os.environ.get("TUNNELDEF_CC_CACHE") or tempfile.gettempdir())
    prefix = cache / "tunneldef-cc" / "cloudcompare-python"
    if not (prefix / "bin" / "CloudCompare").is_file():
        tmp = cache / "tunneldef-cc" / f"unpack-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        with tarfile.open(TARBALL) as tar:
            tar.extractall(tmp, filter="tar")
        if not prefix.exists():
            (tmp / "cloudcompare-python").rename(prefix)
        shutil.rmtree(tmp, ignore_errors=True)
    return prefix


_FOUND: list[Runtime] = []


def find_runtime() -> Runtime:
    """The runtime to test with (found or unpacked once per process).

    Raises
    ------
    Unavailable
        If the shared build is absent or no Python 3.11 packages can be given to it.
    """
    if not _FOUND:
        _FOUND.append(Runtime(_prefix(), _site_packages()))
    return _FOUND[0]


#: Survey-sized offset of the test clouds: CloudCompare must apply a global shift.
SURVEY_OFFSET = (512000.0, 5611000.0, 310.0)


def write_pair(
    out_dir: Path,
    *,
    seed: int = 0,
    length: float = 20.0,
    density: float = 60.0,
    deformations: tuple | None = None,
):
    """A small synthetic pair (about 22 k points each at the defaults) in survey coordinates,
    written as ``ref.ply`` and ``cmp.ply``; returns ``(ref_path, cmp_path)``.

    Coordinates are rounded to a 2**-10 m grid, so CloudCompare's float32 local coordinates
    (after its global shift) hold them exactly and the core sees the same numbers in both
    hosts. A roof sag of 50 mm at chainage 10 m; a side chamber so the position along the axis
    is determined. ``deformations`` (``tunneldef.synth.DeformationSpec``) replace the sag.
    """
    from tunneldef.synth import DeformationSpec, PairSpec, TunnelSpec, make_pair

    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(length=length, chamber=True, density=density, outlier_fraction=0.0),
            deformations=deformations
            or (DeformationSpec(kind="roof_sag", chainage=min(10.0, length / 2), amplitude=0.05),),
            translation=(1.5, -0.8, 0.3),
            seed=seed,
        )
    )
    return _write_survey(out_dir, pair)


def write_network_pair(out_dir: Path, *, seed: int = 3, density: float = 150.0):
    """A small synthetic drift network pair (a 40 m drift, a cross-cut through it and a dead
    end: ``test_network.small_network``; a 19 mm wall bulge on the cross-cut), about 150 k
    points per epoch, in survey coordinates on the 2**-10 m grid, as ``ref.ply`` and
    ``cmp.ply``; returns ``(ref_path, cmp_path)``."""
    from test_network import small_network

    from tunneldef.synth import DeformationSpec
    from tunneldef.synth.network import BranchDeformation, make_network_pair

    bulge = BranchDeformation(1, DeformationSpec("wall_bulge", 19.0, 3.0, 1.5, 0.06, "left"))
    pair = make_network_pair(network=small_network(), deformations=(bulge,), ref_coverage=None,
                             cmp_coverage=None, density=density, drift=0.0, equipment=False,
                             seed=seed, yaw_deg=30.0)
    return _write_survey(out_dir, pair)


def _write_survey(out_dir: Path, pair):
    """Both epochs of ``pair`` in survey coordinates on the 2**-10 m grid (CloudCompare's
    float32 local coordinates then hold them exactly), as ``ref.ply`` and ``cmp.ply``."""
    import numpy as np

    from tunneldef.cloud import Cloud
    from tunneldef.io import write

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, cloud in (("ref", pair.ref), ("cmp", pair.cmp)):
        xyz = np.round((cloud.xyz + SURVEY_OFFSET) * 2**10) / 2**10
        path = out_dir / f"{name}.ply"
        write(path, Cloud(xyz))
        paths.append(path)
    return paths[0], paths[1]
