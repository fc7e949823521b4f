import json
import subprocess
import sys
import urllib.request

import pytest

pytest.importorskip("viser")

from edgerecon.viewer.process import start_viewer_process
from tests.viewer._runs import write_run


def test_view_cli_serves_the_web_client_and_stops_with_its_parent(tmp_path):
    run = write_run(tmp_path / "run", num_tasks=2)
    proc = start_viewer_process(run, port=0, nice=0)
    try:
        assert proc.url.startswith("http://127.0.0.1:")
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        with opener.open(proc.url, timeout=30) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
        assert proc.alive()
    finally:
        proc.stop()
    assert not proc.alive()


def test_view_cli_missing_folder_and_a_gone_parent(tmp_path, capsys):
    from edgerecon.cli import main

    assert main(["view", str(tmp_path / "nope"), "--json"]) == 2
    captured = capsys.readouterr()
    assert "not found" in captured.err and captured.out == ""
    # --parent-pid of a process that is gone: the viewer starts, then ends by itself.
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    run = write_run(tmp_path / "run", num_tasks=1)
    assert main(["view", str(run), "--port", "0", "--json", "--parent-pid", gone]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[0])
    assert info["url"] == f"http://127.0.0.1:{info['port']}"  # nothing else on stdout


def test_run_with_view_serves_while_it_runs_and_stops_after(tiny_dataset, tmp_path, capsys):
    from edgerecon.cli import main

    out = tmp_path / "run"
    args = ["run", "--dataset", str(tiny_dataset), "--deadline", "20", "--frames", "0:1"]
    args += ["--no-background-updates", "--out", str(out), "--view", "--view-port", "0", "--json"]
    assert main(args) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert len(result["tasks"]) == 1
    url = captured.err.split("viewer at ")[1].split()[0]
    assert url.startswith("http://127.0.0.1:")
    assert (out / "rig.json").exists()
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    with pytest.raises(OSError):  # the viewer ended with the run
        opener.open(url, timeout=5)
