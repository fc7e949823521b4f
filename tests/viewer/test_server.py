"""The viewer's server against a client speaking viser's protocol (no browser)."""

import numpy as np
import pytest

pytest.importorskip("viser")

from edgerecon.viewer.layout import initial_view
from edgerecon.viewer.server import RunViewer, ViewerConfig
from edgerecon.viewer.wire import WireClient
from tests.conftest import ring_rig
from tests.viewer._runs import FG_RGB, append_task, scene_cloud, task_metrics, write_run

# The watcher thread is slowed down so that the test drives refresh() itself.
MANUAL = ViewerConfig(port=0, poll_s=3600.0, point_budget=4000)


def test_a_new_tasks_cloud_reaches_a_connected_client(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=2, finished=False)
    with RunViewer(run, MANUAL) as viewer:
        client = WireClient(viewer.port)
        try:
            first = client.next_cloud("/cloud", timeout_s=20)
            assert first is not None
            points, colors = first
            assert len(points) == 4000  # the point budget
            fg = (colors == FG_RGB).all(axis=1)
            assert fg.sum() >= 2000  # the foreground keeps at least half of it
            assert points[fg, 0].mean() == pytest.approx(0.1, abs=0.02)  # task 1's shift
            append_task(run, task_metrics(2, rss_mb=812.4), scene_cloud(shift=1.0))
            assert viewer.refresh() == 1
            second = client.next_cloud("/cloud", timeout_s=20)
            assert second is not None
            points, colors = second
            fg = (colors == FG_RGB).all(axis=1)
            assert points[fg, 0].mean() == pytest.approx(1.0, abs=0.02)
        finally:
            client.close()
        assert "**task 2**" in viewer._gui["task"].content
        assert "0.80" in viewer._gui["task"].content  # r of task 2
        assert "3 tasks (0 failed, 0 degraded), memory 812 MB" in viewer._gui["status"].content
        assert "cam4" in viewer._gui["task"].content and "cam3" not in viewer._gui["task"].content


def test_only_the_newest_of_several_new_tasks_is_drawn(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=1, finished=False)
    with RunViewer(run, MANUAL) as viewer:
        sent = viewer.stats["clouds_sent"]
        for k in (1, 2, 3):
            append_task(run, task_metrics(k), scene_cloud(shift=0.1 * k, inferred=k == 3))
        assert viewer.refresh() == 3
        assert viewer.stats["clouds_sent"] == sent + 1
        assert viewer.stats["clouds_skipped"] == 2
        assert viewer._shown.task == 3
        # Task 3's cloud has the inferred attribute: the menu offers it.
        assert "measured / inferred" in viewer._gui["coloring"].options
        # The chosen cameras are highlighted.
        colors = [tuple(f.color) for f in viewer._frusta]
        assert colors[3] != colors[0] and colors.count(colors[0]) == 4
        # Replay: back to task 1.
        assert viewer.replay(1)
        assert viewer._shown.task == 1
        assert "measured / inferred" not in viewer._gui["coloring"].options
        # A resume with cam1 placed again replaces rig.json: its frustum moves.
        from edgerecon.io.calibration import load_rig, save_rig
        from tests.quality.test_calibration import moved

        before = np.array(viewer._frusta[1].position)
        save_rig(run / "rig.json", moved(load_rig(run / "rig.json"), 1, (0.5, 0, 0), (0, 0, 0)))
        viewer.refresh()
        after = np.array(viewer._frusta[1].position)
        assert np.linalg.norm(after - before) == pytest.approx(0.5, abs=1e-6)


def test_initial_view_looks_at_the_scene_with_the_rigs_up():
    rig = ring_rig(5)
    view = initial_view(rig)
    assert np.allclose(view.look_at, [0, 0, 1.0], atol=1e-6)
    assert np.allclose(view.up, [0, 0, 1])
    assert view.position[2] > 1.5  # above the cameras
    assert np.linalg.norm(view.position[:2]) > 4.0  # outside the ring


def test_initial_view_is_in_metres_for_a_millimetre_rig():
    import dataclasses

    from edgerecon.geometry import Camera

    rig_m = ring_rig(5)
    cams = [
        Camera(name=c.name, width=c.width, height=c.height, K=c.K, R=c.R, t=c.t * 1000.0)
        for c in rig_m
    ]
    rig_mm = dataclasses.replace(rig_m, cameras=tuple(cams), unit="mm")
    a, b = initial_view(rig_m), initial_view(rig_mm)
    assert np.allclose(a.position, b.position) and np.allclose(a.look_at, b.look_at)


def test_a_long_runs_chart_shows_its_newest_tasks_and_removed_clouds_are_not_drawn(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=6, finished=False)
    config = ViewerConfig(port=0, poll_s=3600.0, point_budget=4000, chart_tasks=3)
    with RunViewer(run, config) as viewer:
        viewer.refresh()
        x = viewer._gui["chart"].data[0]
        np.testing.assert_array_equal(x, [3, 4, 5])
        assert viewer._shown.task == 5
        # The run removed its older clouds (--keep-clouds): replaying one of them shows
        # nothing new and says so; a kept one is drawn.
        import shutil

        from edgerecon.runtime.state import task_dir

        for m in viewer.run.tasks[:4]:
            shutil.rmtree(task_dir(run, m.time_index))
        assert not viewer.replay(2)
        assert viewer._shown.task == 5
        assert viewer.replay(4) and viewer._shown.task == 4
        append_task(run, task_metrics(6), scene_cloud(shift=0.6))
        assert viewer.refresh() == 1
        np.testing.assert_array_equal(viewer._gui["chart"].data[0], [4, 5, 6])
    with pytest.raises(ValueError, match="chart_tasks"):
        ViewerConfig(chart_tasks=1)
