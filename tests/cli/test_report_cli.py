import json

from edgerecon.cli import main
from tests.viewer._runs import write_run


def test_report_cli_writes_figures(tmp_path, capsys):
    run = write_run(tmp_path / "run", num_tasks=3)
    assert main(["report", str(run), "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)["figures"]
    assert set(figures) >= {"latency", "summary"}
    assert (run / "report" / "summary.png").stat().st_size > 10_000
    assert main(["report", str(tmp_path / "missing")]) == 2
