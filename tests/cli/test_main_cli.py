"""The command line as a whole: global options anywhere, logs, suggestions, tables, config
files, phases."""

from __future__ import annotations

import json
import re

import pytest

from edgerecon.cli import main
from edgerecon.cli._common import print_table
from edgerecon.config import ReconstructionConfig
from edgerecon.configfile import (
    ConfigError,
    build,
    dump_toml,
    field_docs,
    load_config_file,
)
from edgerecon.optimize.controller import ControllerConfig
from edgerecon.runtime.config import RuntimeConfig


def test_suggestions(capsys):
    with pytest.raises(SystemExit):
        main(["recon", "--dataset", "x"])
    assert "did you mean 'reconstruct'?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["info", "--datset", "x"])
    assert "did you mean --dataset?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", "a.ply", "b.ply", "--jsn"])
    assert "did you mean --json?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", "a.ply", "--part", "foregruond"])
    assert "did you mean 'foreground'?" in capsys.readouterr().err


def test_global_options_anywhere_and_log_file(tiny_dataset, tmp_path, capsys):
    log = tmp_path / "run.log"
    out = tmp_path / "rec"
    args = ["reconstruct", "--dataset", str(tiny_dataset), "-t", "1", "--no-dense", "-r", "0.5"]
    assert main(["-v", *args, "-o", str(out), "-v", "--log-file", str(log)]) == 0
    err = capsys.readouterr().err
    # -v before and after the subcommand add up (-vv: debug lines on the terminal).
    assert re.search(r"^\d\d:\d\d:\d\d DEBUG ", err, re.M)
    text = log.read_text()
    assert re.search(
        r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} INFO MainThread edgerecon", text, re.M
    )
    assert "open the dataset:" in text and "reconstruct:" in text
    assert main([*args, "-o", str(out), "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_tables_are_not_cut_when_piped(capsys):
    long = "/a/very/long/path/that/does/not/fit/in/eighty/columns/camera_0_video.mp4"
    print_table("t", ["camera", "size", "source"], [["cam0", "1080x1920", long]])
    out = capsys.readouterr().out
    assert long in out and "1080x1920" in out and "…" not in out


def test_config_round_trip_and_errors(tmp_path):
    sections = {
        "reconstruction": ReconstructionConfig(scale=0.7, camera_ids=(0, 2, 3)),
        "runtime": RuntimeConfig(deadline_s=1.5, golden_timeout_s=0.8),
        "controller": ControllerConfig(deadline_s=1.5, margin_s=0.25, r_min=0.4),
    }
    path = tmp_path / "c.toml"
    path.write_text(dump_toml(sections))
    data = load_config_file(path)
    assert build(ReconstructionConfig, data["reconstruction"]) == sections["reconstruction"]
    assert build(RuntimeConfig, data["runtime"]) == sections["runtime"]
    cc = build(ControllerConfig, data["controller"], overrides={"deadline_s": 1.5})
    assert cc == sections["controller"]
    assert "deadline_s" not in data["controller"]  # the controller's comes from [runtime]
    # Docstrings become comments.
    assert field_docs(RuntimeConfig)["golden_timeout_s"].startswith("How long the front-end")
    assert "# How long the front-end waits" in path.read_text()
    # Mistakes name the key and the closest one.
    with pytest.raises(
        ConfigError, match=r"'reconstruction.sparse_config.max_featurs'.*max_features"
    ):
        build(ReconstructionConfig, {"sparse_config": {"max_featurs": 10}}, where="reconstruction")
    with pytest.raises(ConfigError, match=r"runtime.golden_timeout_s must be a number"):
        build(RuntimeConfig, {"deadline_s": 1.0, "golden_timeout_s": "soon"}, where="runtime")
    path.write_text("[runtim]\ndeadline_s = 1\n")
    with pytest.raises(ConfigError, match=r"unknown table \[runtim\]; did you mean 'runtime'"):
        load_config_file(path)
    with pytest.raises(ValueError, match="scale"):  # the class's own validation
        build(ReconstructionConfig, {"scale": 2.0})


def test_reconstruct_config_file_phases_and_cameras(tiny_dataset, tmp_path, capsys):
    cfg = tmp_path / "my.toml"
    cfg.write_text(
        "[reconstruction]\nscale = 0.5\ndense = false\n"
        "[reconstruction.sparse_config]\nmax_features = 500\n"
    )
    out = tmp_path / "a"
    base = ["reconstruct", "--dataset", str(tiny_dataset), "-t", "2", "--json"]
    assert main([*base, "-o", str(out), "--config", str(cfg)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["scale"] == 0.5 and summary["num_dense_points"] is None
    assert summary["config"]["sparse_config"]["max_features"] == 500
    # Every phase is timed and they account for the wall time.
    phases = summary["phases"]
    assert {"open the dataset", "reconstruct", "write the outputs"} <= set(phases)
    assert sum(phases.values()) == pytest.approx(summary["wall_s"], rel=0.1)
    # The effective configuration loads again; an option typed on the command line wins.
    assert (
        main([*base, "-o", str(tmp_path / "b"), "--config", str(out / "config.toml"), "-r", "0.6"])
        == 0
    )
    again = json.loads(capsys.readouterr().out)
    assert again["scale"] == 0.6 and again["config"]["sparse_config"]["max_features"] == 500
    # Camera errors name the option, the ids and the names.
    assert main([*base, "-o", str(tmp_path / "c"), "--cameras", "0,1"]) == 2
    err = capsys.readouterr().err
    assert (
        "--cameras must name at least 3 distinct cameras, got 2" in err
        and "ids 0-4 = cam0, cam1" in err
    )
    assert main([*base, "-o", str(tmp_path / "c"), "--cameras", "0,1,cam7"]) == 2
    assert "unknown camera 'cam7'" in capsys.readouterr().err
