"""Config tree: paper defaults, TOML round trip, validation; atomic text outputs."""

from __future__ import annotations

from pathlib import Path

import pytest

from tunneldef.config import Config, dump_config, load_config
from tunneldef.errors import ConfigError
from tunneldef.textfiles import write_csv, write_json, write_text_atomic


def test_paper_defaults() -> None:
    c = Config()
    assert c.deformation.k == 3  # Table 3
    assert c.centerline.kde_bandwidth == 0.1  # §4.1
    assert c.centerline.degree == 3  # §3.1.4


def test_dump_loads_back_to_the_same_config(tmp_path: Path) -> None:
    changed = Config().replace(danger={"threshold": 0.021}, deformation={"k": 5})
    p = tmp_path / "c.toml"
    p.write_text(dump_config(changed))
    assert load_config(p) == changed


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[nope]\nx = 1\n", r"unknown config section \[nope\]"),
        ("[deformation]\nk = 'three'\n", r"deformation.k must be int"),
        ("[deformation]\nk = true\n", r"deformation.k must be int"),
        ("[danger\n", r"not valid TOML"),
        ("[deformation]\nmethod = 'm3c2'\n", r"deformation.method must be one of 'robust', 'knn'"),
        ("[danger]\nrule = 'max'\n", r"danger.rule must be one of"),
        ("[registration]\nmethod = 'icp'\n", r"registration.method must be one of"),
        ("[centerline]\nvertical = 'up'\n", r"centerline.vertical must be one of"),
    ],
)
def test_bad_config_files(tmp_path: Path, text: str, message: str) -> None:
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(p)


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "none.toml")


def test_int_is_accepted_for_float() -> None:
    assert Config().replace(danger={"threshold": 1}).danger.threshold == 1.0


def test_atomic_text_write_keeps_old_file_on_failure(tmp_path: Path) -> None:
    p = tmp_path / "s.json"
    write_json(p, {"a": 1})
    before = p.read_bytes()
    with pytest.raises(TypeError):
        write_json(p, {"a": object()})
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["s.json"]
    write_text_atomic(p, "x")
    assert p.read_text() == "x"


def test_csv_quotes_commas(tmp_path: Path) -> None:
    p = write_csv(tmp_path / "t.csv", [{"a": 1.5, "b": "x,y"}, {"a": None, "b": 'q"'}])
    assert p.read_text() == 'a,b\n1.5,"x,y"\n,"q"""\n'


def test_json_has_no_nan(tmp_path: Path) -> None:
    import json

    import numpy as np

    p = write_json(tmp_path / "n.json", {"a": float("nan"), "b": np.array([1.0, np.inf]),
                                         "c": [np.float32(2.5), {"d": np.nan}]})
    assert json.loads(p.read_text()) == {"a": None, "b": [1.0, None], "c": [2.5, {"d": None}]}


def test_configs_share_no_mutable_default() -> None:
    import dataclasses

    from tunneldef import config as cfgmod

    # a list or dict default is copied per instance, never shared
    @dataclasses.dataclass
    class Holder:
        values: list = cfgmod._p([1, 2], "test")

    a, b = Holder(), Holder()
    a.values.append(3)
    assert b.values == [1, 2]
