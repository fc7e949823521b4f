"""Smoke tests of ``edgerecon simulate``."""

from __future__ import annotations

import json

import numpy as np

from edgerecon.cli import main


def test_simulate_json(capsys):
    assert main(["simulate", "--deadline", "5", "10", "--tasks", "40", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["deadline_s"] for r in out["runs"]] == [5.0, 10.0]
    run5 = out["runs"][0]
    assert len(run5["rows"]) == 40
    assert run5["rows"][0]["phase"] == "golden"
    assert run5["summary"]["search_steps"] > out["runs"][1]["summary"]["search_steps"]
    for row in run5["rows"]:
        assert 0.3 <= row["scale"] <= 1.0 and 3 <= row["num_cameras"] <= 7


def test_simulate_table_and_errors(capsys):
    assert main(["simulate", "--deadline", "7.5", "--tasks", "20", "--load-step", "10:1.5"]) == 0
    out = capsys.readouterr().out
    assert "search steps" in out and "per task" in out
    assert main(["simulate", "--deadline", "7.5", "--tasks", "0"]) == 2
    assert "--tasks" in capsys.readouterr().err
    assert main(["simulate", "--deadline", "-3"]) == 2
    assert "deadline_s" in capsys.readouterr().err


def test_select_cameras_from_a_visibility_file(tmp_path, capsys):
    from edgerecon.optimize import synthetic_visibility

    vis = synthetic_visibility(8, 800, seed=0)[0]
    np.save(tmp_path / "vis.npy", vis)
    assert main(["select-cameras", str(tmp_path / "vis.npy"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    sels = {s["num_cameras"]: s for s in out["mapping"]["selections"]}
    assert sorted(sels) == list(range(3, 9))
    assert sels[8]["camera_ids"] == list(range(8))
    assert all(s["optimal"] for s in sels.values())
    assert (
        main(["select-cameras", str(tmp_path / "vis.npy"), "--available", "0", "2", "4", "6"]) == 0
    )
    table = capsys.readouterr().out
    assert "brute_force" in table and "0 2 4 6" in table
    assert main(["select-cameras", str(tmp_path / "missing.npy")]) == 2
    assert "not found" in capsys.readouterr().err
    np.save(tmp_path / "bad.npy", np.full((4, 5), 3))
    assert main(["select-cameras", str(tmp_path / "bad.npy")]) == 2
    assert "0/1" in capsys.readouterr().err


def test_simulate_late_share(capsys):
    def misses(*extra):
        assert main(["simulate", "--deadline", "7.5", "--tasks", "200", "--json", *extra]) == 0
        summary = json.loads(capsys.readouterr().out)["runs"][0]["summary"]
        return summary["misses_converged"] / summary["tasks_converged"]

    assert misses("--late-share", "0.1") < 0.18 < 0.3 < misses()
    assert main(["simulate", "--deadline", "7.5", "--late-share", "0.6"]) == 2
    assert "late_share" in capsys.readouterr().err
