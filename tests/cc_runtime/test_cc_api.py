"""Every class, function and method the stand-in ``tests/fake_pycc.py`` fakes exists in the
real ``pycc`` (introspected inside CloudCompare by ``dump_api.py``) with a compatible
signature: each positional-argument count the fake accepts is accepted by one of the real
overloads, named arguments have the real names, static methods are static there too."""

from __future__ import annotations

import inspect
import json
import re
import types

import fake_pycc
import pytest

from .runner import HERE

pytestmark = pytest.mark.cloudcompare

#: Names in the stand-in that are test switches or helpers, not part of the faked API.
NOT_FAKED_API = {"install", "STRIDE0_ARRAYS", "SCALE_GETTER_BUG", "PROCESSED_EVENTS", "types"}
#: Methods the stand-in documents as test helpers (not in the binding).
HELPERS = {("ccGLMatrix", "matrix")}


@pytest.fixture(scope="module")
def real_api(cc_runtime, tmp_path_factory) -> dict:
    work = tmp_path_factory.mktemp("cc_api")
    out = work / "api.json"
    proc = cc_runtime.run_script(HERE / "dump_api.py", [], workdir=work, script_args=[str(out)])
    assert out.is_file(), proc.stdout[-2000:] + proc.stderr[-2000:]
    return json.loads(out.read_text(encoding="utf-8"))


def _split_params(text: str) -> list[str]:
    """Top-level comma split of a pybind11 parameter list."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch in "[(" or ch == "{":
            depth += 1
        elif ch in "])" or ch == "}":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
        else:
            cur += ch
    if cur.strip():
        out.append(cur.strip())
    return out


def overloads(doc: str, name: str) -> list[list[tuple[str, bool]]]:
    """``[(param name, has default), ...]`` per overload in a pybind11 docstring (``self``
    dropped); ``*args``-only catch-all signatures are skipped."""
    found = []
    for line in doc.splitlines():
        m = re.match(rf"^(?:\d+\. )?{re.escape(name)}\((.*)\) -> ", line.strip())
        if not m:
            continue
        params = []
        for p in _split_params(m.group(1)):
            pname = p.split(":")[0].split("=")[0].strip()
            if pname in ("self", "*args", "**kwargs"):
                continue
            params.append((pname, "=" in p))
        if m.group(1).strip() != "*args, **kwargs":
            found.append(params)
    return found


def _fake_params(func) -> tuple[int, float, list[str]]:
    """(required, max positional, names) of a fake callable (self dropped)."""
    sig = inspect.signature(func)
    params = [p for p in sig.parameters.values() if p.name != "self"]
    required = sum(
        1 for p in params if p.default is p.empty and p.kind in (p.POSITIONAL_OR_KEYWORD,)
    )
    var = any(p.kind == p.VAR_POSITIONAL for p in params)
    names = [p.name for p in params if p.kind == p.POSITIONAL_OR_KEYWORD]
    return required, float("inf") if var else len(names), names


def compare(fake_obj, real_doc: str, name: str, where: str) -> list[str]:
    """Problems with one faked callable against its real docstring."""
    sigs = overloads(real_doc, name)
    if not sigs and name == "__init__" and real_doc.startswith("Initialize self."):
        return []  # not constructible from Python there: the fake's constructor is its own
    if not sigs:
        return [f"{where}: no signature found in the real docstring"]
    required, most, names = _fake_params(fake_obj)
    counts = range(required, (required if most == float("inf") else int(most)) + 1)
    problems = []
    for k in counts:
        if not any(sum(not d for _, d in s) <= k <= len(s) for s in sigs):
            problems.append(f"{where}: the fake accepts {k} argument(s), the real does not")
    for i, pname in enumerate(names):
        real_names = {s[i][0] for s in sigs if i < len(s) and not s[i][0].startswith("arg")}
        if real_names and pname not in real_names:
            problems.append(f"{where}: argument {i} is {pname!r} here, {sorted(real_names)} there")
    return problems


def faked_api() -> list[tuple[str, str | None, object]]:
    """(class or function name, method name or None, object) of everything the fake fakes."""
    items = []
    for name, obj in vars(fake_pycc).items():
        if name.startswith("_") or name in NOT_FAKED_API:
            continue
        if isinstance(obj, types.FunctionType) and obj.__module__ == fake_pycc.__name__:
            items.append((name, None, obj))
        elif inspect.isclass(obj) and obj.__module__ == fake_pycc.__name__:
            items.append((name, "", obj))
            for mname, member in vars(obj).items():
                if (mname.startswith("_") and mname not in ("__init__", "__len__")) or (
                    name,
                    mname,
                ) in HELPERS:
                    continue
                if isinstance(member, (types.FunctionType, staticmethod)):
                    items.append((name, mname, member))
        elif name in ("PointCoordinateType", "ScalarType"):
            items.append((name, "", obj))
    return items


def check(real: dict) -> tuple[list[str], int]:
    """(problems, number of callables compared)."""
    problems, compared = [], 0
    for cname, mname, obj in faked_api():
        if cname not in real:
            problems.append(f"{cname}: not in the real pycc")
            continue
        if mname is None:  # module function
            problems += compare(obj, real[cname]["doc"], cname, cname)
            compared += 1
            continue
        if mname == "":
            continue
        members = real[cname].get("members", {})
        where = f"{cname}.{mname}"
        if mname not in members:
            problems.append(f"{where}: not in the real pycc")
            continue
        is_static = isinstance(obj, staticmethod)
        if is_static != (members[mname]["kind"] == "staticmethod"):
            problems.append(
                f"{where}: static here is {is_static}, there it is a {members[mname]['kind']}"
            )
        func = obj.__func__ if is_static else obj
        problems += compare(func, members[mname]["doc"], mname, where)
        compared += 1
    return problems, compared


def test_every_faked_name_exists_with_a_compatible_signature(real_api):
    problems, compared = check(real_api)
    assert compared >= 60, f"only {compared} callables compared"
    assert problems == [], "\n".join(problems)


def test_the_comparison_catches_a_wrong_fake(real_api):
    def addScalarField(self, name, values, extra):  # noqa: N802 - a required third argument
        pass

    def setMethodTitle(self, text, colour=None):  # noqa: N802 - wrong name, one optional too many
        pass

    doc = real_api["ccPointCloud"]["members"]["addScalarField"]["doc"]
    assert compare(addScalarField, doc, "addScalarField", "x") == [
        "x: the fake accepts 3 argument(s), the real does not"
    ]
    doc = real_api["ccProgressDialog"]["members"]["setMethodTitle"]["doc"]
    assert any("accepts 2" in p for p in compare(setMethodTitle, doc, "setMethodTitle", "y"))
