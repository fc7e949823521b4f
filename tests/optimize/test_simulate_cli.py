"""Smoke tests of ``edgerecon simulate``."""

from __future__ import annotations

import json

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
    assert main(["simulate", "-d", "7.5", "--tasks", "20", "--load-step", "10:1.5"]) == 0
    out = capsys.readouterr().out
    assert "search steps" in out and "per task" in out
    assert main(["simulate", "-d", "7.5", "--tasks", "0"]) == 2
    assert "--tasks" in capsys.readouterr().err
    assert main(["simulate", "-d", "-3"]) == 2
    assert "deadline_s" in capsys.readouterr().err
