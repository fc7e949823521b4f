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


def test_view_cli_json_and_a_missing_folder(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "edgerecon", "view", str(tmp_path / "nope"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "not found" in out.stderr
    assert out.stdout == ""  # nothing (not even viser's banner) on stdout
    # --parent-pid of a process that is gone: the viewer serves, then exits by itself.
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    run = write_run(tmp_path / "run", num_tasks=1)
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "edgerecon",
            "view",
            str(run),
            "--port",
            "0",
            "--json",
            "--parent-pid",
            gone,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0
    info = json.loads(out.stdout.strip().splitlines()[0])
    assert info["url"] == f"http://127.0.0.1:{info['port']}"


def test_run_with_view_serves_while_it_runs_and_stops_after(tiny_dataset, tmp_path, capsys):
    from edgerecon.cli import main

    out = tmp_path / "run"
    args = ["run", "--dataset", str(tiny_dataset), "--deadline", "20", "--frames", "0:2"]
    args += ["--no-background-updates", "--out", str(out), "--view", "--view-port", "0", "--json"]
    assert main(args) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert len(result["tasks"]) == 2
    url = captured.err.split("viewer at ")[1].split()[0]
    assert url.startswith("http://127.0.0.1:")
    assert (out / "rig.json").exists()
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    with pytest.raises(OSError):  # the viewer ended with the run
        opener.open(url, timeout=5)
