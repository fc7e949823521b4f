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


def test_evaluate_reads_openmvs_style_ply(tmp_path, capsys):
    from tests.io.test_ply import _openmvs_style_ply

    rng = np.random.default_rng(2)
    ref = rng.uniform(0, 1, (2000, 3))
    pred = ref[:1000] + [0.004, 0, 0]  # half of it, 4 mm off
    views = [[0, 1, 2]] * len(pred)
    _openmvs_style_ply(tmp_path / "mvs.ply", pred, np.zeros((len(pred), 3)), views)
    write_ply(tmp_path / "ref.ply", PointCloud(points3D=ref), unit="m")
    args = ["evaluate", str(tmp_path / "mvs.ply"), str(tmp_path / "ref.ply")]
    assert main([*args, "-d", "0.005", "0.003", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    at5, at3 = out["scores"]
    assert at5["precision"] == 1.0 and at3["precision"] < 0.1
    # Recall: the ref points near the predicted half (the other half is ~1/25 covered).
    assert 0.5 <= at5["recall"] < 0.6
    assert out["unit"] == "m" and out["max_distance"] == 0.01


def test_evaluate_default_thresholds_are_relative_to_the_rig(tiny_dataset, tmp_path, capsys):
    from edgerecon.io import open_dataset
    from edgerecon.runtime.config import median_camera_distance

    rig = open_dataset(tiny_dataset).rig
    pts = np.random.default_rng(0).uniform(0, 1, (300, 3))
    write_ply(tmp_path / "a.ply", PointCloud(points3D=pts))
    args = ["evaluate", str(tmp_path / "a.ply"), str(tmp_path / "a.ply")]
    assert main([*args, "--dataset", str(tiny_dataset), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    dist = median_camera_distance(rig)
    assert out["thresholds"] == [0.01 * dist, 0.02 * dist]
    assert out["scale_from"].startswith("median camera distance")
    assert main([*args, "--dataset", str(tiny_dataset)]) == 0
    text = capsys.readouterr().out
    assert "1% and 2% of the median camera distance" in " ".join(text.split())
    # Without a rig: shares of the reference's size, and said so.
    assert main([*args, "-d", "1%", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "bounding-box" in out["scale_from"]
    assert main([*args, "-d", "x"]) == 2
    assert "lengths or percentages" in capsys.readouterr().err


def test_evaluate_unlabelled_cloud_against_the_foreground(tiny_dataset, tmp_path, capsys):
    from edgerecon.synth import GroundTruth

    gt = GroundTruth.open(tiny_dataset)
    fg = gt.reference_cloud(2, "foreground", min_views=1)
    bg = gt.reference_cloud(2, "background", min_views=1)
    # Unlabelled: the whole scene, with background points far from the actors.
    far = bg.points3D[np.linalg.norm(bg.points3D - fg.points3D.mean(axis=0), axis=1) > 2.0]
    write_ply(tmp_path / "scene.ply", PointCloud(points3D=np.concatenate([fg.points3D, far])))
    base = ["evaluate", str(tmp_path / "scene.ply"), "--gt", str(tiny_dataset), "--time", "2"]
    assert main([*base, "--part", "foreground", "-d", "0.01", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["pred_selection"] == "crop" and out["num_pred"] == len(fg)
    assert out["scores"][0]["fscore"] == 1.0
    assert main([*base, "--part", "foreground", "-d", "0.01"]) == 0
    assert "has no labels" in capsys.readouterr().out


def test_evaluate_measured_only_leaves_out_inferred_points(tmp_path, capsys):
    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 1, (1000, 3))
    wrong = ref[:250] + [0.2, 0, 0]  # a completed "floor" 20 cm off the truth
    pred = PointCloud(points3D=np.concatenate([ref, wrong])).with_inferred(
        np.r_[np.zeros(1000, bool), np.ones(250, bool)]
    )
    write_ply(tmp_path / "pred.ply", pred)
    write_ply(tmp_path / "ref.ply", PointCloud(points3D=ref))
    args = ["evaluate", str(tmp_path / "pred.ply"), str(tmp_path / "ref.ply"), "-d", "0.01"]
    assert main([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["inferred"] == 250 and out["num_pred"] == 1250 and not out["measured_only"]
    assert abs(out["scores"][0]["precision"] - 0.8) < 0.01  # the wrong fifth
    assert main([*args, "--json", "--measured-only"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["inferred"] == 250 and out["num_pred"] == 1000 and out["measured_only"]
    assert out["scores"][0]["precision"] == 1.0
    assert main([*args, "--measured-only"]) == 0
    text = capsys.readouterr().out
    assert "250 of 1,250 points inferred" in text and "--measured-only" in text
    # A cloud without the property: all measured, nothing left out.
    (tmp_path / "old.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n"
    )
    old = ["evaluate", str(tmp_path / "old.ply"), str(tmp_path / "ref.ply"), "-d", "0.01"]
    assert main([*old, "--json", "--measured-only"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["inferred"] == 0 and out["num_pred"] == 1
