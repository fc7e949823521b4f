"""``edgerecon run``: options checked before any work, the output folder's rules, exit codes,
Ctrl-C."""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import pytest

import edgerecon.pipeline
import edgerecon.runtime.online
import edgerecon.runtime.session
from edgerecon.cli import build_parser, main


def _run(tiny_dataset, out, *extra):
    return main(
        [
            "run",
            "--dataset",
            str(tiny_dataset),
            "--out",
            str(out),
            "--deadline",
            "20",
            "--no-background-updates",
            *extra,
        ]
    )


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--frames", "100:"], "selects no timestamp"),
        (["--fixed", "0"], "--fixed must be a scale in (0, 1]"),
        (["--fixed", "0.5", "--cameras", "0,0,1"], "--cameras must name at least 3 distinct"),
        (["--cameras", "0,1,2"], "give --fixed SCALE too"),
        (["--inject-fault", "1:kill"], "needs --engine ray"),
        (["--inject-fault", "x:stall"], "--inject-fault must be TASK:stall|crash|kill"),
        (["--resume", "--overwrite"], "exclude each other"),
    ],
)
def test_bad_options_are_refused_before_any_work(tiny_dataset, tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    t0 = time.perf_counter()
    assert _run(tiny_dataset, out, *extra) == 2
    assert time.perf_counter() - t0 < 3.0, "refused before the set-up, not after"
    assert message in capsys.readouterr().err
    assert not out.exists(), "no empty output folder left behind"


def test_unwritable_out_is_refused_at_once(tiny_dataset, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    assert _run(tiny_dataset, tmp_path / "file" / "out", "--frames", "0:1") == 2
    assert "cannot write there" in capsys.readouterr().err


def test_run_refuses_a_used_folder_resumes_and_overwrites(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "run"
    assert _run(tiny_dataset, out, "--frames", "0:2", "--fixed", "0.6", "--json") == 0
    first = json.loads(capsys.readouterr().out)
    assert [t["time_index"] for t in first["tasks"]] == [0, 1]
    # The task clouds say which points are inferred (PLY 'uchar inferred').
    from edgerecon.io.ply import read_ply_meta

    assert "inferred" in read_ply_meta(out / "tasks" / "000001" / "fg.ply").vertex_properties
    from edgerecon.viewer.rundir import RunFolder

    merged = RunFolder(out).cloud(1)
    assert merged is not None and "inferred" in merged.attributes
    # A finished run is not replaced silently.
    assert _run(tiny_dataset, out, "--frames", "0:2", "--fixed", "0.6") == 2
    assert "not empty" in capsys.readouterr().err
    assert _run(tiny_dataset, out, "--frames", "0:3", "--fixed", "0.6", "--resume", "--json") == 0
    resumed = json.loads(capsys.readouterr().out)
    assert [t["time_index"] for t in resumed["tasks"]] == [0, 1, 2]
    assert resumed["summary"]["tasks"] == 3
    # Every task says the process's memory; the summary its first / last task's and peak.
    if sys.platform.startswith("linux"):
        rss = [t["rss_mb"] for t in resumed["tasks"]]
        assert all(50 < x < 20_000 for x in rss), rss
        mem = resumed["summary"]["memory_mb"]
        assert mem["first"] == rss[0] and mem["last"] == rss[-1]
        assert mem["peak"] >= rss[-1]
    # --overwrite starts again: no stale task folder of the old run remains.
    assert _run(tiny_dataset, out, "--frames", "1:2", "--fixed", "0.6", "--overwrite") == 0
    assert sorted(p.name for p in (out / "tasks").iterdir()) == ["000001"]
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 1


def test_failed_tasks_exit_3_with_the_summary(tiny_dataset, tmp_path, capsys, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", boom)
    assert _run(tiny_dataset, tmp_path, "--frames", "0:2", "--fixed", "0.6") == 3
    err = capsys.readouterr().err
    assert "2 of 2 tasks failed" in err
    assert json.loads((tmp_path / "summary.json").read_text())["failed"] == 2


def test_ctrl_c_writes_the_summary_and_prints_resume(tiny_dataset, tmp_path, capsys, monkeypatch):
    real = edgerecon.runtime.session.frame_defects

    def interrupt(frames, config=None):
        if frames.time_index == 1:
            raise KeyboardInterrupt
        return real(frames, config)

    monkeypatch.setattr(edgerecon.runtime.session, "frame_defects", interrupt)
    assert _run(tiny_dataset, tmp_path, "--frames", "0:3", "--fixed", "0.6") == 130
    err = capsys.readouterr().err
    assert "interrupted after 1 tasks" in err and "--resume" in err
    assert f"--out {tmp_path}" in err
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["tasks"] == 1


def test_run_help_documents_exit_codes(capsys):
    parser = build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(["run", "--help"])
    text = capsys.readouterr().out
    assert "exit codes:" in text and "130" in text and "tasks failed" in text.replace("\n", " ")


def test_export_of_a_run_task_composes_its_merged_cloud(tiny_dataset, tmp_path, capsys):
    """A run stores a task's foreground and each background version once; exporting the
    task's folder gives the merged cloud (the run's reader composes it), or its foreground."""
    import numpy as np

    from edgerecon.io.ply import read_ply
    from edgerecon.viewer.rundir import RunFolder

    out = tmp_path / "run"
    args = ["run", "--dataset", str(tiny_dataset), "--out", str(out), "--deadline", "20"]
    assert main([*args, "--frames", "0:3", "--fixed", "0.6"]) == 0
    capsys.readouterr()
    task = out / "tasks" / "000002"
    merged = RunFolder(out).cloud(2)
    assert merged is not None and (merged.labels > 0).any()
    ply = tmp_path / "t2.ply"
    assert main(["export", str(task), "--to", "ply", "-o", str(ply), "--max-range", "none"]) == 0
    got = read_ply(ply)
    np.testing.assert_array_equal(got.points3D, merged.points3D.astype(got.points3D.dtype))
    np.testing.assert_array_equal(got.labels, merged.labels)
    fg = tmp_path / "fg.ply"
    cmd = [
        "export",
        str(task),
        "--to",
        "ply",
        "--cloud",
        "fg",
        "-o",
        str(fg),
        "--max-range",
        "none",
    ]
    assert main(cmd) == 0
    assert len(read_ply(fg)) == int((merged.labels > 0).sum())
    # The whole run as a PLY sequence (Blender, Houdini, Open3D): one file per kept task.
    seq = tmp_path / "seq"
    capsys.readouterr()
    cmd = ["export", str(out), "--to", "ply", "-o", str(seq), "--max-range", "none", "--json"]
    assert main(cmd) == 0
    report = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in seq.iterdir()) == ["000000.ply", "000001.ply", "000002.ply"]
    assert report["unit"] == "m" and report["missing"] == 0
    np.testing.assert_array_equal(
        read_ply(seq / "000002.ply").points3D, merged.points3D.astype(got.points3D.dtype)
    )
    # The foreground alone, one task; a task the retention removed is said, not an error.
    (out / "tasks" / "000001" / "fg.ply").unlink()
    assert main([*cmd[:-1], "--cloud", "fg", "-o", str(tmp_path / "seqfg"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["missing"] == 1 and len(report["clouds"]) == 2
    assert len(read_ply(tmp_path / "seqfg" / "000002.ply")) == int((merged.labels > 0).sum())
    assert main([*cmd, "--time", "7"]) == 2
    assert "no task cloud to export at time 7" in capsys.readouterr().err


def test_a_deadline_as_a_share_of_the_original_pipeline(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    """``--deadline 40%``: the original pipeline is timed on the first timestamp before the
    first task, the deadline is 40 % of it, the summary gives the online / original ratio,
    and a resumed run keeps that measurement (it is not timed again)."""
    out = tmp_path / "run"
    args = ["--frames", "1:3", "--deadline", "40%", "--json"]
    assert _run(tiny_dataset, out, *args) == 0
    summary = json.loads(capsys.readouterr().out)["summary"]
    original = summary["original_s"]
    assert original > 0 and summary["deadline_share"] == 0.4
    assert summary["deadline_s"] == pytest.approx(round(0.4 * original, 3))
    assert summary["online_over_original"] == pytest.approx(
        summary["avg_time_s"] / original, abs=1e-3
    )
    state = json.loads((out / "state.json").read_text())
    assert state["original"]["time_index"] == 1 and state["original"]["seconds"] == original
    assert state["original"]["stages"]["dense.depth"] > 0
    # The effective configuration keeps the share (loaded again, it measures again).
    assert "deadline_share = 0.4" in (out / "config.toml").read_text()

    def timed_again(*a, **k):
        raise AssertionError("a resumed run measured the original pipeline again")

    monkeypatch.setattr(edgerecon.runtime.online, "measure_original", timed_again)
    assert (
        _run(tiny_dataset, out, "--frames", "1:4", "--deadline", "40%", "--json", "--resume") == 0
    )
    resumed = json.loads(capsys.readouterr().out)
    assert resumed["summary"]["tasks"] == 3
    assert resumed["summary"]["deadline_s"] == summary["deadline_s"]
    assert resumed["summary"]["original_s"] == original
    assert {t["deadline_s"] for t in resumed["tasks"]} == {summary["deadline_s"]}


@pytest.mark.parametrize(
    ("value", "message"),
    [("0%", "a share in (0%, 1000%]"), ("-1", "must be > 0 seconds"), ("fast", "seconds (0.6)")],
)
def test_bad_deadlines_are_refused(tiny_dataset, tmp_path, capsys, value, message):
    with pytest.raises(SystemExit) as exc:
        _run(tiny_dataset, tmp_path / "out", "--deadline", value)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_the_resume_command_repeats_a_share():
    from edgerecon.cli._config import parse_deadline
    from edgerecon.cli.run import resume_command

    args = build_parser().parse_args(
        ["run", "--dataset", "d", "--out", "o", "--deadline", "35%", "--frames", "0:9:2"]
    )
    assert args.deadline == parse_deadline("35%")
    assert "--deadline 35% --frames 0:9:2" in resume_command(args)
    args.deadline = parse_deadline("0.75")
    assert "--deadline 0.75 " in resume_command(args)
    args.late_share = 0.1
    assert "--late-share 0.1" in resume_command(args)


def test_late_share_reaches_the_controller(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    assert _run(tiny_dataset, out, "--frames", "0:1", "--late-share", "0.15") == 0
    state = json.loads((out / "state.json").read_text())
    assert state["frontend"]["controller"]["config"]["late_share"] == 0.15
    assert "late_share = 0.15" in (out / "config.toml").read_text()


def test_a_share_from_the_config_file(tiny_dataset, tmp_path, capsys):
    cfg = tmp_path / "share.toml"
    cfg.write_text("[runtime]\ndeadline_share = 0.5\nbackground_updates = false\n")
    out = tmp_path / "run"
    words = ["run", "--dataset", str(tiny_dataset), "--out", str(out), "--frames", "0:1"]
    assert main([*words, "--config", str(cfg), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)["summary"]
    assert summary["deadline_s"] == pytest.approx(round(0.5 * summary["original_s"], 3))
    # Seconds typed on the command line win over the file's share: nothing is measured.
    assert main([*words, "--config", str(cfg), "--deadline", "9", "--overwrite", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)["summary"]
    assert summary["deadline_s"] == 9 and summary["original_s"] is None


def test_the_original_pipeline_is_timed_on_usable_frames(
    tiny_dataset, tmp_path_factory, tmp_path, capsys
):
    """Lights out at the first timestamp, a camera blinded at the next: the original
    pipeline is timed on the first frames every camera can use (said), and a stream with
    none is refused with the way out."""
    import shutil

    import cv2
    import numpy as np

    src = tmp_path_factory.mktemp("dark") / "scene"
    shutil.copytree(tiny_dataset, src)
    black = np.zeros((240, 320, 3), np.uint8)
    for cam in range(5):
        cv2.imwrite(str(src / "frames" / f"cam{cam}" / "000003.png"), black)
    cv2.imwrite(str(src / "frames" / "cam2" / "000004.png"), black)
    words = ["run", "--dataset", str(src), "--deadline", "50%", "--no-background-updates"]
    assert main([*words, "--out", str(tmp_path / "a"), "--frames", "3:6", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads((tmp_path / "a" / "state.json").read_text())["original"]["time_index"] == 5
    assert "time 3: cam0 black" in captured.err and "time 4: cam2 black" in captured.err
    assert main([*words, "--out", str(tmp_path / "b"), "--frames", "3:4"]) == 2
    err = capsys.readouterr().err
    assert "could not be measured" in err and "give --deadline in seconds" in err


def test_adopt_repairs_loop_adopts_resumes_and_stops_adopting(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    """``run --adopt-repairs``'s loop (``run_online`` replaced): each ``RepairDue`` names
    its rig in the dataset and resumes with the models it hands on and the rest of
    ``--duration``; after ``MAX_ADOPTIONS`` the run stops adopting; a rig that is not the
    calibration with cameras placed again is not adopted and the run goes on as it was."""
    import shutil

    import edgerecon.cli.run as cli_run
    from edgerecon.io.dataset import open_dataset
    from edgerecon.runtime.session import RepairDue, RunSummary
    from tests.quality.test_calibration import moved

    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset, root)
    rig = open_dataset(root).rig
    fixes = [moved(rig, 1, (0.0, 0.0, 0.0), (0.0, d, 0.0)) for d in (1.0, 1.5, 2.0)]
    calls = []

    def fake(ds, config, options, out, **kw):
        calls.append((ds.rig, options, kw["scene"]))
        if len(calls) <= len(fixes):
            summary = RunSummary(tasks=len(calls))
            raise RepairDue(summary, [], fixes[len(calls) - 1], scene=f"models {len(calls)}")
        return RunSummary(tasks=9), []

    monkeypatch.setattr(cli_run, "run_online", fake)
    out = tmp_path / "run"
    args = ["run", "--dataset", str(root), "--out", str(out), "--deadline", "20"]
    assert main([*args, "--adopt-repairs", "--duration", "60", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["summary"]["tasks"] == 9
    assert len(calls) == 4
    assert not calls[0][1].resume and calls[0][2] is None
    for i, (used, options, scene) in enumerate(calls[1:]):
        assert options.resume and not options.overwrite
        assert np.allclose(used[1].R, fixes[i][1].R)  # the adopted rig, read from the dataset
        assert scene == f"models {i + 1}"
        assert 0 < options.duration_s < 60  # the rest of the run's --duration
    assert [c[1].adopt_repairs for c in calls] == [True, True, True, False]  # at most 3

    # A repaired rig that is another world frame is not adopted: the run goes on as it was.
    calls.clear()
    fixes[:] = [
        moved(
            moved(moved(rig, 0, (1, 0, 0), (0, 0, 0)), 2, (1, 0, 0), (0, 0, 0)),
            3,
            (1, 0, 0),
            (0, 0, 0),
        )
    ]
    before = (root / "dataset.json").read_text()
    assert main([*args, "--adopt-repairs", "--overwrite", "--json"]) == 0
    capsys.readouterr()
    assert len(calls) == 2 and not calls[1][1].adopt_repairs
    assert (root / "dataset.json").read_text() == before


def test_adopt_repairs_needs_a_dataset_json(tmp_path, capsys):
    from tests.conftest import shared_data

    root = shared_data("utrecht4cam")  # a layout recognised from its files: no dataset.json
    out = tmp_path / "o"
    args = ["run", "--dataset", str(root), "--out", str(out), "--deadline", "1"]
    assert main([*args, "--adopt-repairs"]) == 2
    assert "no dataset.json to name a repaired rig in" in capsys.readouterr().err
    assert not out.exists()  # refused before any work


def test_a_run_that_wrote_a_repaired_rig_says_how_to_take_it(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    import edgerecon.cli.run as cli_run
    from edgerecon.runtime.session import RunSummary

    verdict = {"fits": False, "short": "off: cam1", "repair": "cam1 re-aimed by 2.00 degrees"}

    def fake(ds, config, options, out, **kw):
        return RunSummary(tasks=3, calibration=dict(verdict)), []

    monkeypatch.setattr(cli_run, "run_online", fake)
    out = tmp_path / "run"
    args = ["run", "--dataset", str(tiny_dataset), "--out", str(out), "--deadline", "20"]
    assert main(args) == 0
    assert "calib --dataset" not in capsys.readouterr().err  # no rig written: nothing said
    verdict["repaired_rig_file"] = "rig.repaired.json"
    assert main([*args, "--json"]) == 0
    said = capsys.readouterr()
    json.loads(said.out)  # stdout stays the JSON
    assert f"calib --dataset {tiny_dataset} --adopt {out / 'rig.repaired.json'}" in said.err
    assert "cam1 re-aimed by 2.00 degrees" in said.err and "--resume" in said.err


def test_the_summary_says_each_move_and_one_line_for_a_camera_that_kept_moving():
    from edgerecon.runtime.session import camera_moves_row

    def move(camera, t, turn, across=False):
        return {"camera": camera, "time_index": t, "turn_deg": turn, "across_stop": across}

    sway = [move("cam2", t, 0.4 + 0.1 * k) for k, t in enumerate(range(25, 150, 25))]
    name, text = camera_moves_row([move("cam1", 50, 2.95, True), *sway, move("cam0", 80, 1.0)])
    assert name == "cameras whose view moved"
    assert text == (
        "cam1 across a stop, at time 50 (about 2.95 degrees); "
        "cam2 kept moving: 5 moves recorded, time 25 to 125 (0.40-0.80 degrees); "
        "cam0 at time 80 (about 1.00 degrees)"
    )
