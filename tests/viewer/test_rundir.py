import json

import pytest

from edgerecon.types import EdgereconError
from edgerecon.viewer.rundir import RunFolder, read_run
from tests.viewer._runs import append_task, scene_cloud, task_metrics, write_run


def test_poll_reads_new_tasks_incrementally(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=2, finished=False)
    folder = RunFolder(run)
    assert [m.task for m in folder.poll()] == [0, 1]
    assert folder.poll() == []
    assert folder.rig() is not None and len(folder.rig()) == 5
    assert folder.rig() is folder.rig()  # read once
    # A resume with a camera placed again writes rig.json anew: read again.
    from edgerecon.io.calibration import save_rig
    from tests.quality.test_calibration import moved

    first = folder.rig()
    save_rig(run / "rig.json", moved(first, 1, (0.1, 0.0, 0.0), (0.0, 1.0, 0.0)))
    placed = folder.rig()
    assert placed is not first and placed is folder.rig()
    assert placed[1].center == pytest.approx(moved(first, 1, (0.1, 0, 0), (0, 1, 0))[1].center)
    assert placed[0].center == pytest.approx(first[0].center)
    # A line written in two pieces is read once it is complete.
    line = json.dumps(task_metrics(2).to_dict())
    with open(run / "metrics.jsonl", "a") as f:
        f.write(line[:20])
    assert folder.poll() == []
    with open(run / "metrics.jsonl", "a") as f:
        f.write(line[20:] + "\n")
    assert [m.task for m in folder.poll()] == [2]
    assert not folder.finished and folder.newest_with_cloud().task == 1  # 2 has no cloud
    append_task(run, task_metrics(3), scene_cloud())
    folder.poll()
    assert folder.newest_with_cloud().task == 3
    assert folder.newest_with_cloud(upto=2).task == 1
    assert len(folder.cloud(6)) == len(scene_cloud())


def test_a_new_run_in_the_same_folder_starts_over(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=3)
    folder = read_run(run)
    assert len(folder.tasks) == 3 and folder.finished
    (run / "metrics.jsonl").unlink()  # what a fresh session does first
    (run / "summary.json").unlink()
    append_task(run, task_metrics(0, critical_path_s=9.0), None)
    folder.poll()
    assert folder.resets == 1
    assert [m.critical_path_s for m in folder.tasks] == [9.0]


def test_read_run_names_what_is_missing(tmp_path):
    with pytest.raises(EdgereconError, match="not found"):
        read_run(tmp_path / "nope")
    with pytest.raises(EdgereconError, match="metrics.jsonl"):
        read_run(tmp_path)
