import json

import numpy as np

from edgerecon.cli import main
from edgerecon.io.ply import write_ply
from edgerecon.types import PointCloud


def test_evaluate_json_and_table(tmp_path, capsys):
    pts = np.random.default_rng(0).uniform(0, 1, (500, 3))
    write_ply(tmp_path / "a.ply", PointCloud(points3D=pts))
    write_ply(tmp_path / "b.ply", PointCloud(points3D=pts + [0.5, 0, 0]))
    assert main(["evaluate", str(tmp_path / "a.ply"), str(tmp_path / "a.ply"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["fscore"] for s in out["scores"]] == [1.0, 1.0]
    assert main(["evaluate", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-d", "0.01"]) == 0
    assert "F-score" in capsys.readouterr().out


def test_evaluate_missing_file_is_clean_error(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path / "nope.ply"), str(tmp_path / "nope.ply")]) == 2
    assert "not found" in capsys.readouterr().err
