"""The house's rules that code can check: light shared types, no host in the core."""

from __future__ import annotations

import subprocess
import sys

import pytest

HEAVY = ("skimage", "geomdl", "open3d", "matplotlib", "laspy")


@pytest.mark.parametrize(
    "module", ["tunneldef", "tunneldef.curve", "tunneldef.frame", "tunneldef.cloud",
               "tunneldef.config", "tunneldef.transforms", "tunneldef.spatial"]
)
def test_shared_types_load_no_heavy_library(module: str) -> None:
    code = (f"import sys, {module}; "
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "", f"importing {module} loaded {out}"


def test_plots_leave_pyplot_and_the_backend_alone(tmp_path) -> None:
    code = (
        "import sys, numpy as np, matplotlib\n"
        "matplotlib.use('svg')\n"
        "from tunneldef.report._figures import figures\n"
        "fig, ax = figures().subplots(1, 2, figsize=(4, 2))\n"
        "ax[0].plot([0, 1], [0, 1])\n"
        f"fig.savefig({str(tmp_path / 'f.png')!r})\n"
        "print(matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["svg", "False"]
    assert (tmp_path / "f.png").stat().st_size > 1000


def test_the_core_imports_no_host() -> None:
    code = ("import sys, tunneldef.pipeline, tunneldef.cli; "
            "print(','.join(m for m in ('pycc', 'PySide2', 'PyQt5', 'cccorelib') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == ""


def test_main_verbs_are_exported() -> None:
    import tunneldef

    for name in ("read", "write", "detect", "extract_centerline", "register",
                 "compute_deformation"):
        assert callable(getattr(tunneldef, name)), name
    with pytest.raises(AttributeError):
        tunneldef.no_such_verb  # noqa: B018


def test_long_modules_say_why_they_are_one_idea() -> None:
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = [p for d in ("tunneldef", "plugin", "cloudcompare_scripts")
             for p in (root / d).rglob("*.py")]
    assert len(files) > 20
    missing = []
    for path in files:
        text = path.read_text(encoding="utf-8")
        if text.count("\n") <= 400:
            continue
        doc = " ".join((ast.get_docstring(ast.parse(text)) or "").split())
        if "One idea at this length:" not in doc:
            missing.append(str(path.relative_to(root)))
    assert not missing, f"over 400 lines without saying why they are one idea: {missing}"


def test_the_readme_layout_names_every_module() -> None:
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text(encoding="utf-8")
    layout = readme.split("## Layout", 1)[1].split("\n## ", 1)[0]
    names = {p.name for d in ("tunneldef", "plugin", "cloudcompare_scripts")
             for p in (root / d).rglob("*.py")} - {"__init__.py", "__main__.py"}
    assert len(names) > 40
    missing = sorted(n for n in names if n not in layout)
    assert not missing, f"README's Layout does not name {missing}"
