"""Run inside CloudCompare (``-PYTHON_SCRIPT dump_api.py OUT.json``): dump the public API of the
real ``pycc`` module, every class's members with their pybind11 signature lines, to JSON."""

from __future__ import annotations

import inspect
import json
import sys


def _doc(obj: object) -> str:
    try:
        return inspect.getdoc(obj) or ""
    except Exception:  # noqa: BLE001 - any binding oddity: no doc
        return ""


def describe(obj: object) -> dict:
    """``{"kind", "doc"}`` and, for classes, ``"members"``: name -> {"kind", "doc"}."""
    out = {"kind": type(obj).__name__, "doc": _doc(obj)}
    if inspect.isclass(obj):
        members = {}
        for name in dir(obj):
            if name.startswith("__") and name != "__init__" and name != "__len__":
                continue
            try:
                member = inspect.getattr_static(obj, name)
            except AttributeError:
                continue
            kind = type(member).__name__
            try:
                target = getattr(obj, name)
            except Exception:  # noqa: BLE001 - e.g. a static property needing an instance
                target = member
            members[name] = {"kind": kind, "doc": _doc(target)}
        out["members"] = members
    return out


def main() -> None:
    import pycc

    out = {n: describe(getattr(pycc, n)) for n in dir(pycc) if not n.startswith("_")}
    with open(sys.argv[1], "w", encoding="utf-8") as fh:
        json.dump(out, fh, indent=1, sort_keys=True)


main()
