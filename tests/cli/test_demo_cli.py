import json

from edgerecon.cli import main


def test_demo_runs_online_system_and_reuses_scene(tmp_path, capsys):
    args = [
        "demo",
        "--out",
        str(tmp_path),
        "--num-frames",
        "5",
        "--size",
        "320x240",
        "--no-background-updates",
        "--json",
    ]
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["generated"] is True
    tasks = result["tasks"]
    assert [t["time_index"] for t in tasks] == [0, 1, 2, 3, 4]
    assert tasks[0]["phase"] == "golden"
    assert all(t["status"] == "ok" and t["offline_fscore"] is not None for t in tasks)
    assert result["deadline_s"] > 0 and result["golden"]["seconds"] > 0
    # Like for like with the online tasks: the golden configuration's foreground.
    golden_fg = result["golden_foreground"]
    assert golden_fg["time_index"] == 2 and golden_fg["points"] > 0
    assert 0.0 < golden_fg["fscore"] <= 1.0 and golden_fg["seconds"] > 0
    assert (tmp_path / "run" / "tasks" / "000004" / "fg.ply").exists()
    # A second run finds the scene already generated.
    assert main([*args, "--frames", "0:2"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["generated"] is False and len(again["tasks"]) == 2
    # The closing table says what each F-score scores (the original's whole scene, the online
    # tasks' foreground): not one column of two things.
    assert main([a for a in args if a != "--json"] + ["--frames", "0:3"]) == 0
    out = capsys.readouterr().out
    assert "whole scene (t=2)" in out and "foreground (each task)" in out
    # ... and the foreground of the same time by the golden configuration and by the online
    # task of that time.
    assert "golden foreground" in out and "the task of t=2" in out
    assert out.count("foreground (t=2)") == 2
