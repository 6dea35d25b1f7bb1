"""The `tunneldef` command: help, config, errors (one line, exit 2) and the main job end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tunneldef import __version__
from tunneldef.cli import main


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_version_and_help(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert __version__ in capsys.readouterr().out
    for command in ["info", "synth", "centerline", "register", "detect", "demo", "config"]:
        with pytest.raises(SystemExit) as exc:
            main([command, "--help"])
        assert exc.value.code == 0
        assert "usage: tunneldef" in capsys.readouterr().out


def test_config_dump_lists_paper_defaults(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "config", "--dump")
    assert code == 0
    assert "k = 3  # paper §4.3, Table 3" in out
    assert "kde_bandwidth = 0.1  # paper §4.1" in out


def test_config_file_overrides_and_rejects_unknown_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = tmp_path / "good.toml"
    good.write_text("[danger]\nthreshold = 0.02\n")
    code, out, _ = run(capsys, "config", "--config", str(good))
    assert code == 0 and "threshold = 0.02" in out
    bad = tmp_path / "bad.toml"
    bad.write_text("[danger]\nthreshhold = 0.02\n")
    code, _, err = run(capsys, "config", "--config", str(bad))
    assert code == 2
    assert err.strip() == "tunneldef: error: unknown config key danger.threshhold"


def test_missing_input_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run(capsys, "info", str(tmp_path / "nope.las"))
    assert code == 2
    assert err.count("\n") == 1 and "not found" in err


def test_console_script_exit_code(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "tunneldef.cli", "detect", str(tmp_path / "a.ply"),
         str(tmp_path / "b.ply"), "-o", str(tmp_path / "o.ply")],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("tunneldef: error:") and "Traceback" not in proc.stderr


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    from tunneldef import synth

    spec = synth.PairSpec(
        tunnel=synth.TunnelSpec(length=24.0, density=300.0, equipment=True, roughness=0.03),
        deformations=(synth.DeformationSpec(kind="roof_sag", chainage=12.0, length=4.0,
                                            width=2.0, amplitude=0.04),),
        cmp_shift=1.0, yaw_deg=123.0, seed=7,
    )
    pair = synth.make_pair(spec)
    d = tmp_path_factory.mktemp("pair")
    paths = synth.write_pair(pair, d, fmt="ply")
    return pair, paths, d


def test_same_file_and_output_over_input_are_refused(
    pair_files, capsys: pytest.CaptureFixture[str]  # noqa: ANN001
) -> None:
    _, paths, d = pair_files
    ref, cmp = str(paths["ref"]), str(paths["cmp"])
    code, _, err = run(capsys, "detect", ref, ref, "-o", str(d / "x.ply"))
    assert code == 2 and "same file" in err
    before = Path(cmp).read_bytes()
    code, _, err = run(capsys, "detect", ref, cmp, "-o", cmp)
    assert code == 2 and "same file as input" in err
    assert Path(cmp).read_bytes() == before


def test_info_reports_axis_and_length(
    pair_files, capsys: pytest.CaptureFixture[str]  # noqa: ANN001
) -> None:
    pair, paths, _ = pair_files
    code, out, _ = run(capsys, "info", str(paths["ref"]))
    assert code == 0
    assert f"points:     {len(pair.ref):,}" in out
    length = float(out.split("length:")[1].split("m")[0])
    assert abs(length - 24.0) < 1.0  # 0.5-99.5 % extent of a 24 m tunnel


@pytest.mark.slow
def test_detect_end_to_end_output_contract(
    pair_files, capsys: pytest.CaptureFixture[str]  # noqa: ANN001
) -> None:
    from tunneldef.io import read

    pair, paths, d = pair_files
    out, summary, sections = d / "result.ply", d / "summary.json", d / "sections.csv"
    code, _, err = run(capsys, "detect", str(paths["ref"]), str(paths["cmp"]), "-o", str(out),
                       "--summary", str(summary), "--sections", str(sections),
                       "--threshold", "0.02")
    assert code == 0, err
    res = read(out)
    cmp = read(paths["cmp"])
    # same points, same order, original attributes, coordinates in the reference frame
    assert len(res) == len(cmp)
    for name in ["deformation", "deformation_horizontal", "deformation_vertical", "chainage",
                 "danger"]:
        assert name in res.fields
    for name in cmp.fields:
        np.testing.assert_array_equal(res.fields[name], cmp.fields[name])
    s = json.loads(summary.read_text())
    t = np.array(s["transform_compared_to_reference"])
    moved = cmp.xyz @ t[:3, :3].T + t[:3, 3]
    np.testing.assert_allclose(res.xyz, moved, atol=1e-4)
    # registration error against the true motion: millimetre level (rough rock fixes the
    # position along the axis; 2.1 mm measured)
    err_rms = np.sqrt(np.mean(np.sum((res.xyz - pair.truth.cmp_xyz_in_ref) ** 2, axis=1)))
    assert err_rms < 0.008
    # the 40 mm roof sag is seen in its core, with the right sign, within 30 % (the cylinder
    # average and the shell mask trim a narrow peak on rough rock: -29 mm of -37.5 measured)
    core = (pair.truth.displacement < -0.035) & (pair.truth.label == 0)
    assert core.sum() > 50
    truth = float(np.median(pair.truth.displacement[core]))
    measured = float(np.median(res.fields["deformation"][core]))
    assert 1.3 * truth < measured < 0.7 * truth, (measured, truth)
    flagged = res.fields["danger"][core].mean()
    assert flagged > 0.5, (flagged, measured, s["danger_zones"])
    assert sections.read_text().count("\n") > 10
    assert s["danger_threshold_m"] == pytest.approx(0.02)


def test_detect_refuses_different_units(
    pair_files, capsys: pytest.CaptureFixture[str]  # noqa: ANN001
) -> None:
    from tunneldef.cloud import Cloud
    from tunneldef.io import write

    pair, paths, d = pair_files
    mm = d / "cmp_mm.ply"
    write(mm, Cloud(pair.cmp.xyz * 1000.0))
    code, _, err = run(capsys, "detect", str(paths["ref"]), str(mm), "-o", str(d / "o2.ply"))
    assert code == 2 and "scale" in err
    assert not (d / "o2.ply").exists()


def test_detect_refuses_a_blob(
    pair_files, capsys: pytest.CaptureFixture[str]  # noqa: ANN001
) -> None:
    from tunneldef.cloud import Cloud
    from tunneldef.io import write

    _, paths, d = pair_files
    blob = d / "blob.ply"
    write(blob, Cloud(np.random.default_rng(0).normal(size=(5000, 3))))
    code, _, err = run(capsys, "detect", str(paths["ref"]), str(blob), "-o", str(d / "o3.ply"))
    assert code == 2 and "elongated" in err


def test_detect_refuses_an_undetermined_axial_position(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tunneldef import synth

    # a perfect prism: nothing fixes where the compared stretch lies along the axis
    pair = synth.make_pair(synth.PairSpec(tunnel=synth.TunnelSpec(length=20.0, density=80.0),
                                          yaw_deg=30.0, seed=3))
    paths = synth.write_pair(pair, tmp_path)
    code, _, err = run(capsys, "detect", str(paths["ref"]), str(paths["cmp"]), "-o",
                       str(tmp_path / "o.ply"))
    assert code == 2 and "along the tunnel is undetermined" in err
    assert "the common stretch" in err and "no feature" in err
    assert not (tmp_path / "o.ply").exists()


def test_an_undetermined_position_says_whether_a_feature_was_seen() -> None:
    """Where the slide's strongest feature is not confirmed by the section images (a small
    chamber beside a conveyor whose coal changed reads like a prism's noise), the reason
    says where it looked rather than that the drift has no chamber."""
    from tunneldef.pipeline import _why_undetermined

    assert "no features along the axis" in _why_undetermined({})
    seen = _why_undetermined({"axial_feature_window": {"chainage": 56.5, "shift": 0.0,
                                                       "spread": 1.5}})
    assert "that the section images confirm" in seen
    assert "near chainage 56.5 m" in seen and "1.50 m either way" in seen
    thin = _why_undetermined({"axial_feature_window": {"chainage": 3.0, "shift": 0.0,
                                                       "spread": float("inf")}})
    assert "too few points" in thin


def test_synth_refuses_a_pair_too_large_for_memory_and_streams_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import tunneldef.cli as cli
    from tunneldef.io import read

    monkeypatch.setattr(cli, "_available_memory", lambda: 50_000_000)  # 50 MB free
    code, _, err = run(capsys, "synth", str(tmp_path / "a"), "--length", "30", "--density",
                       "400", "--format", "laz")
    assert code == 2 and err.count("\n") == 1 and "--stream" in err
    assert not (tmp_path / "a" / "ref.laz").exists()
    code, _, err = run(capsys, "synth", str(tmp_path / "a"), "--length", "30", "--density",
                       "400", "--format", "laz", "--stream", "--quiet")
    assert code == 0, err
    truth = json.loads((tmp_path / "a" / "truth.json").read_text())
    assert truth["points"]["ref"] == len(read(tmp_path / "a" / "ref.laz")) > 100_000
