import cv2
import numpy as np
import pytest

from edgerecon.report import FIGURES, figure, load_runs, stage_means, summary_rows, write_report
from edgerecon.types import EdgereconError
from tests.viewer._runs import append_task, task_metrics, write_run


def test_report_writes_every_figure_as_a_png(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=5)
    paths = write_report([run], tmp_path / "figs")
    assert list(paths) == list(FIGURES)
    for name, path in paths.items():
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 150 and image.shape[1] > 600, name
        assert image.std() > 10  # not a blank page
    page = cv2.imread(str(paths["summary"]))
    assert page.shape[0] > page.shape[1]  # a portrait page


def test_figures_plot_the_runs_numbers(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=5)
    append_task(run, task_metrics(5, status="failed", error="no frames"), None)
    runs = load_runs([run])
    ax = figure("latency", runs).axes[0]
    line = ax.lines[0]
    assert np.allclose(line.get_xdata(), [0, 1, 2, 3, 4, 5])
    assert np.allclose(line.get_ydata()[:5], [1.0, 1.25, 1.5, 1.75, 2.0])
    assert np.isnan(line.get_ydata()[5])  # the failed task breaks the line
    missed = next(ln for ln in ax.lines if ln.get_marker() == "x")
    assert np.allclose(missed.get_xdata(), [3, 4])  # 1.75 and 2.0 s > 1.5 s
    failed = next(ln for ln in ax.lines if ln.get_marker() == "|")
    assert list(failed.get_xdata()) == [5]
    ax_r, ax_n = figure("configuration", runs).axes
    assert np.allclose(ax_r.lines[0].get_ydata(), [1.0, 0.9, 0.8, 0.7, 0.6])
    assert set(ax_n.lines[0].get_ydata()) == {4}
    q = figure("quality", runs).axes[0]
    assert np.allclose(q.lines[0].get_ydata(), [0.9, 0.85, 0.8, 0.75, 0.7])
    bg = figure("background", runs).axes[0]
    assert list(bg.lines[0].get_ydata()) == [0, 0, 1, 1, 2]
    assert stage_means(runs[0]) == pytest.approx({"sfm": 0.5, "fg_dense.depth": 0.9})
    assert not figure("memory", runs).axes[0].lines  # no task recorded its memory
    rows = dict(summary_rows(runs[0]))
    assert "memory: first / last / largest task (MB)" not in rows
    assert rows["deadline misses (all / after convergence)"].startswith("2 / ")
    assert rows["tasks / failed / degraded"].startswith("6 / 1 / ")


def test_configurations_finer_than_golden_fit_the_scale_axis(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=2)
    append_task(run, task_metrics(2, scale=1.6), None)
    ax_r, _ = figure("configuration", load_runs([run])).axes
    assert np.allclose(ax_r.lines[0].get_ydata(), [1.0, 0.9, 1.6])
    assert ax_r.get_ylim()[1] >= 1.6 and "finer than golden" in ax_r.get_ylabel()


def test_several_runs_share_a_figure_labelled_by_deadline(tmp_path):
    a = write_run(tmp_path / "a", num_tasks=3)
    b = tmp_path / "b"
    b.mkdir()
    for k in range(3):
        append_task(b, task_metrics(k, deadline_s=5.0), None)
    runs = load_runs([a, b])
    assert [r.label for r in runs] == ["deadline 1.5 s", "deadline 5 s"]
    ax = figure("latency", runs).axes[0]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [r.label for r in runs]


def test_report_refuses_folders_without_tasks(tmp_path):
    with pytest.raises(EdgereconError, match="metrics.jsonl"):
        load_runs([tmp_path])
    (tmp_path / "metrics.jsonl").write_text("")
    with pytest.raises(EdgereconError, match="no task"):
        load_runs([tmp_path])


def test_background_versions_with_back_end_epochs_plot_in_order(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=4)  # counters 0, 0, 1, 1
    runs = load_runs([run])
    for m, epoch in zip(runs[0].tasks, (0, 0, 0, 1), strict=True):
        m.bg_epoch = epoch  # a restarted back-end counts from 1 again (runs that record epochs)
    ax = figure("background", runs).axes[0]
    assert list(ax.lines[0].get_ydata()) == [0, 0, 1, 2]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["v0.0", "v0.1", "v1.1"]


def test_summary_names_the_distance_of_the_ground_truth_fscore(tmp_path):
    import json

    run = write_run(tmp_path / "run", num_tasks=2)
    rows = dict(summary_rows(load_runs([run])[0]))
    assert "avg. F-score of FG (vs ground truth)" in rows  # no ground truth: no distance
    summary = {"tasks": 2, "avg_offline_fscore": 0.5, "offline_threshold": 0.0173, "unit": "m"}
    (run / "summary.json").write_text(json.dumps(summary))
    rows = dict(summary_rows(load_runs([run])[0]))
    assert rows["avg. F-score of FG (vs ground truth, d = 0.0173 m)"] == "0.500"
    assert not any(k.startswith("calibration") for k in rows)  # no check made


def test_summary_gives_the_calibration_verdict(tmp_path):
    import json

    run = write_run(tmp_path / "run", num_tasks=2)
    verdict = {"time": 65, "fits": False, "off": ["cam_2"], "short": "off: cam_2"}
    (run / "summary.json").write_text(json.dumps({"tasks": 2, "calibration": verdict}))
    rows = dict(summary_rows(load_runs([run])[0]))
    assert rows["calibration against the frames (time 65)"] == "off: cam_2"
    verdict["repair"] = "cam_2 re-aimed by 2.01 degrees: the calibration then fits"
    (run / "summary.json").write_text(json.dumps({"tasks": 2, "calibration": verdict}))
    rows = dict(summary_rows(load_runs([run])[0]))
    assert rows["calibration against the frames (time 65)"] == (
        "off: cam_2; calib --write: cam_2 re-aimed by 2.01 degrees: the calibration then fits"
    )
    # A run's: the rig is in its folder.
    verdict |= {"fits": True, "short": "fits", "repaired_rig_file": "rig.repaired.json"}
    verdict["repair"] = (
        "cam_2 re-aimed by 1.98 degrees (the turn taken off its frames since it moved)"
    )
    (run / "summary.json").write_text(json.dumps({"tasks": 2, "calibration": verdict}))
    rows = dict(summary_rows(load_runs([run])[0]))
    assert rows["calibration against the frames (time 65)"] == (
        "fits; rig.repaired.json: cam_2 re-aimed by 1.98 degrees (the turn taken off its frames "
        "since it moved)"
    )
    assert not any(k.startswith("cameras placed again") for k in rows)
    # A resume that went on with cam_2 placed again (``runtime.state.Recalibration``).
    placed = {
        "from_task": 55,
        "cameras": ["cam_2"],
        "moved": [0.0135],
        "turned_deg": [2.91],
        "previous_rig": "rig.0.json",
    }
    (run / "summary.json").write_text(
        json.dumps({"tasks": 2, "unit": "m", "calibration": verdict, "recalibrations": [placed]})
    )
    rows = dict(summary_rows(load_runs([run])[0]))
    assert rows["cameras placed again at a --resume"] == (
        "from task 55: cam_2 (moved 0.0135 m, turned 2.91 degrees)"
    )


def test_the_stage_figure_is_the_critical_path(tmp_path):
    """Stages a task records after its cloud (``AFTER_CRITICAL_PATH``: a golden task's SfM
    for pi(N'), the online estimate, ...) are not drawn as part of its critical path."""
    run = write_run(tmp_path / "run", num_tasks=0)
    after = {"sfm_mapping": 0.2, "online_quality": 0.01, "scene_update_after": 0.03}
    append_task(run, task_metrics(0, stages={"scene": 0.3, "fg_dense.depth": 0.4, **after}), None)
    append_task(run, task_metrics(1, stages={"scene": 0.5, "online_quality": 0.01}), None)
    runs = load_runs([run])
    assert stage_means(runs[0]) == pytest.approx({"scene": 0.4, "fg_dense.depth": 0.2})
    ax = figure("stages", runs).axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["scene", "fg_dense.depth"]


def test_the_original_pipeline_measured_by_the_run_is_drawn_and_summed_up(tmp_path):
    import json

    run = write_run(tmp_path / "run", num_tasks=5, finished=False)
    assert load_runs([run])[0].original_s is None
    (run / "state.json").write_text(json.dumps({"original": {"seconds": 6.0}}))
    runs = load_runs([run])  # in progress: from the run state
    assert runs[0].original_s == 6.0
    ax = figure("latency", runs).axes[0]
    assert any(ln.get_linestyle() == ":" and ln.get_ydata()[0] == 6.0 for ln in ax.lines)
    rows = dict(summary_rows(runs[0]))
    assert rows["online / original"] == "0.250"  # tasks of 1.0-2.0 s, 1.5 s on average
    (run / "summary.json").write_text(json.dumps({"tasks": 5, "original_s": 3.0}))
    assert load_runs([run])[0].original_s == 3.0


def test_the_memory_figure_follows_each_tasks_resident_memory(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=0)
    for k, rss in enumerate([500.0, 620.5, 610.0, 640.0]):
        append_task(run, task_metrics(k, rss_mb=rss, wall_time=1000.0 + 30.0 * k), None)
    runs = load_runs([run])
    line = figure("memory", runs).axes[0].lines[0]
    assert np.allclose(line.get_xdata(), [0.0, 0.5, 1.0, 1.5])  # minutes
    assert np.allclose(line.get_ydata(), [500.0, 620.5, 610.0, 640.0])
    rows = dict(summary_rows(runs[0]))
    assert rows["memory: first / last / largest task (MB)"] == "500 / 640 / 640"


def test_the_summary_page_says_moved_and_turned_back_cameras_with_long_rows_wrapped(tmp_path):
    """The page has the run table's rows of cameras whose view moved and were turned back,
    each long text wrapped in its cell and the whole table within its part of the page (a
    calibration verdict with a repair was cut at the page's edge); the quality plot marks
    the task that saw a move."""
    import json

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from edgerecon.report import camera_moves_at

    run = write_run(tmp_path / "run", num_tasks=4)
    move = {"camera": "cam2", "time_index": 4, "turn_deg": 2.07, "across_stop": False}
    append_task(run, task_metrics(4, camera_moves=[move], stabilised={"cam2": 1.98}), None)
    verdict = {
        "time": 116,
        "fits": True,
        "short": "fits",
        "repaired_rig_file": "rig.repaired.json",
        "repair": "cam2 re-aimed by 1.98 degrees (the turn taken off its frames since it moved)",
    }
    summary = {
        "tasks": 5,
        "calibration": verdict,
        "camera_moves": [move],
        "stabilised": {"cam2": {"tasks": 88, "unmeasured": 0, "mean_deg": 1.99, "max_deg": 2.01}},
    }
    (run / "summary.json").write_text(json.dumps(summary))
    runs = load_runs([run])
    rows = dict(summary_rows(runs[0]))
    assert rows["cameras whose view moved"] == "cam2 at time 4 (about 2.07 degrees)"
    assert rows["cameras turned back onto their view (knocked, swaying)"] == (
        "cam2: 88 tasks, 1.99 degrees on average, 2.01 at most"
    )
    assert camera_moves_at(runs[0]) == [(4, ["cam2"])]
    quality = figure("quality", runs).axes[0]
    assert any(t.get_text().strip() == "cam2 moved" for t in quality.texts)
    for several in ([run], [run, run]):
        page = figure("summary", load_runs(several))
        renderer = FigureCanvasAgg(page).get_renderer()
        page.draw(renderer)
        table_axes = [ax for ax in page.axes if ax.tables]
        assert len(table_axes) == len(several)
        for ax in table_axes:
            box = ax.get_window_extent()
            (table,) = ax.tables
            texts = [c.get_text().get_text() for c in table.get_celld().values()]
            calib = next(t for t in texts if t.startswith("fits;"))
            assert "\n" in calib  # wrapped
            assert " ".join(calib.split()) == " ".join(
                rows[next(k for k in rows if k.startswith("calibration"))].split()
            )
            for cell in table.get_celld().values():
                cb = cell.get_window_extent(renderer)
                assert box.y0 - 1 <= cb.y0 and cb.y1 <= box.y1 + 1  # within the table's part
                text = cell.get_text().get_window_extent(renderer)
                assert text.x1 <= cb.x1 + 1 and text.x0 >= cb.x0 - 1  # not cut at its edge
