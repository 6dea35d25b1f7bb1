"""Write the reference fingerprints of ``detect`` on fixed synthetic pairs.

``tests/test_golden.py`` runs the same pairs and checks every output field against
``golden.json``: bit for bit (its hash), or, where the last bits differ, the same NaN count and
sums within 1e-9 m per point. A change that is meant to move results regenerates the file:
``python tests/golden/make_golden.py`` (and the commit says why the results moved).

The file also records the versions of the libraries whose arithmetic the results depend on
(:func:`environment`): another numpy, scipy or Open3D orders floating-point work differently,
and the test then holds the fields to what a surveyor reads, not to their last bits.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))


LIBRARIES = ("numpy", "scipy", "open3d", "scikit-image", "geomdl", "laspy")


def environment() -> dict[str, str]:
    """Python's and the numerical libraries' versions the fingerprints were taken with, and the
    processor: numpy and OpenBLAS choose their SIMD kernels by it, which orders sums differently
    (the same versions on two processor models moved a registration by 0.15 mm)."""
    import platform
    from importlib.metadata import version

    env = {"python": platform.python_version()}
    env.update({name: version(name) for name in LIBRARIES})
    env["cpu"] = _processor()
    return env


def _processor() -> str:
    """The processor's model name and the SIMD extensions numpy dispatches to on it."""
    import platform

    model = ""
    try:
        info: dict[str, str] = {}
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            key, _, value = line.partition(":")
            info.setdefault(key.strip().lower(), value.strip())
            if not line.strip():
                break  # the first processor's block
        # a virtual machine may name only the vendor ("AMD EPYC"): family, model and
        # stepping tell two generations apart (they ordered sums differently: 0.15 mm)
        model = " ".join(
            info[k] if k == "model name" else f"{k.replace(' ', '-')}={info[k]}"
            for k in ("model name", "cpu family", "model", "stepping") if info.get(k)
        )
    except OSError:
        pass
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
        simd = [k for k in __cpu_dispatch__ if __cpu_features__.get(k)]
    except ImportError:  # a numpy without these internals: the model name alone
        simd = []
    return " ".join([platform.machine(), model or platform.processor(), *simd]).strip()


def pairs() -> dict[str, object]:
    """The fixed pairs: the quick demo and a curved, arched, sparse pair."""
    from tunneldef import synth
    from tunneldef.demo import demo_spec

    curved = synth.PairSpec(
        tunnel=synth.TunnelSpec(
            length=30.0, section=synth.SectionSpec(kind="arch"), density=120.0,
            noise_sigma=0.012, radius=80.0, chamber=True, chamber_chainage=18.0,
            roughness=0.02,
        ),
        deformations=(
            synth.DeformationSpec(kind="roof_sag", chainage=12.0, length=3.0, width=1.5,
                                  amplitude=0.03),
        ),
        cmp_shift=1.0,
        seed=3,
    )
    return {"demo_quick": demo_spec(quick=True), "curved_arched": curved}


def fingerprint(spec: object) -> dict[str, object]:
    """Hashes (and leading values, for diagnosis) of every field ``detect`` writes."""
    from tunneldef import synth
    from tunneldef.config import Config
    from tunneldef.pipeline import detect

    pair = synth.make_pair(spec)
    # the checks are recorded, not enforced: the fingerprint is of what detect computes (the
    # curved rough pair is refused by default: its two centrelines differ by 3.7 cm)
    res = detect(pair.ref, pair.cmp, Config().replace(quality={"enforce": False}))
    out: dict[str, object] = {"fields": {}, "points": len(res.cloud)}
    for name in sorted(res.cloud.fields):
        a = np.ascontiguousarray(res.cloud.fields[name])
        f = a.astype(np.float64)
        ok = np.isfinite(f)
        out["fields"][name] = {
            "dtype": str(a.dtype),
            "sha256": hashlib.sha256(a.tobytes()).hexdigest(),
            "head": [float(v) for v in a[:8]],
            "nan": int((~ok).sum()),
            "sum": float(f[ok].sum()),
            "abs_sum": float(np.abs(f[ok]).sum()),
        }
    out["transform"] = np.asarray(res.transform).tolist()
    # the input's bounds: a pose is compared by how far it moves these corners, since a
    # rotation's last digits move survey-size translations by millimetres
    out["bounds"] = [pair.cmp.xyz.min(axis=0).tolist(), pair.cmp.xyz.max(axis=0).tolist()]
    out["zones"] = len(res.zones)
    out["sections"] = len(res.sections)
    out["failed_checks"] = res.quality.to_dict()["failed"] if res.quality else []
    return out


def main() -> None:
    data: dict[str, object] = {"environment": environment()}
    data.update({name: fingerprint(spec) for name, spec in pairs().items()})
    (HERE / "golden.json").write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {HERE / 'golden.json'}")


if __name__ == "__main__":
    main()
