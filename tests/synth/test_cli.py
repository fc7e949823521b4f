"""Smoke tests of ``edgerecon synth`` and ``edgerecon evaluate --gt``."""

from __future__ import annotations

import json

import numpy as np

from edgerecon.cli import main
from edgerecon.io.ply import write_ply
from edgerecon.synth import GroundTruth


def test_synth_cli_writes_a_dataset(tmp_path, capsys):
    out = tmp_path / "scene"
    args = [
        "synth",
        "--preset",
        "demo",
        "--out",
        str(out),
        "--frames",
        "2",
        "--seed",
        "3",
        "--size",
        "96x72",
        "--background-frames",
        "1",
        "--cameras",
        "4",
        "--json",
    ]
    assert main(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["num_cameras"] == 4 and report["num_frames"] == 2
    assert report["image_size"] == [96, 72]
    gt = GroundTruth.open(out)
    assert gt.num_frames == 2 and len(gt.rig) == 4
    assert gt.meta["config"]["seed"] == 3
    # Existing output is protected, bad options are clean errors.
    assert main(args) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(["synth", "--out", str(tmp_path / "x"), "--cameras", "2"]) == 2
    assert "num_cameras" in capsys.readouterr().err


def test_evaluate_against_ground_truth(small_dataset, tmp_path, capsys):
    gt = GroundTruth.open(small_dataset.path)
    ref = gt.reference_cloud(1, "foreground", min_views=1)
    pred_path = tmp_path / "pred.ply"
    write_ply(pred_path, ref)
    base = ["evaluate", str(pred_path), "--gt", str(small_dataset.path), "--time", "1"]
    assert main([*base, "--json", "-d", "0.01", "0.02"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["fscore"] for s in out["scores"]] == [1.0, 1.0]
    seen = out["scores_min_views"][0]
    assert seen["recall"] == 1.0 and seen["precision"] < 1.0  # some points seen by one camera
    assert seen["num_ref"] < out["scores"][0]["num_ref"]
    # Shifted by 3 d: the F-score collapses.
    shifted = ref.select(np.arange(len(ref)))
    write_ply(
        tmp_path / "shifted.ply",
        type(ref)(points3D=shifted.points3D + 0.03 / np.sqrt(3), labels=shifted.labels),
    )
    assert (
        main(
            [
                "evaluate",
                str(tmp_path / "shifted.ply"),
                "--gt",
                str(small_dataset.path),
                "--time",
                "1",
                "--json",
                "-d",
                "0.01",
            ]
        )
        == 0
    )
    assert json.loads(capsys.readouterr().out)["scores"][0]["fscore"] < 0.5
    # Background points in PRED are dropped for --part foreground (by their label).
    both = gt.reference_cloud(1, "all", min_views=1)
    write_ply(tmp_path / "both.ply", both)
    assert (
        main(
            [
                "evaluate",
                str(tmp_path / "both.ply"),
                "--gt",
                str(small_dataset.path),
                "--time",
                "1",
                "--json",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["num_pred"] == len(ref) and out["scores"][0]["fscore"] == 1.0
    # The table form prints both references.
    assert main(base) == 0
    text = capsys.readouterr().out
    assert "F-score" in text and ">= 2 cameras" in text


def test_evaluate_gt_errors(small_dataset, tmp_path, capsys):
    pred = tmp_path / "p.ply"
    write_ply(pred, GroundTruth.open(small_dataset.path).reference_cloud(0))
    assert main(["evaluate", str(pred), "--gt", str(small_dataset.path)]) == 2
    assert "--time" in capsys.readouterr().err
    assert main(["evaluate", str(pred), "--gt", str(small_dataset.path), "--time", "9"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert main(["evaluate", str(pred)]) == 2
    assert "--gt" in capsys.readouterr().err
    assert main(["evaluate", str(pred), "--gt", str(tmp_path)]) == 2
    assert "scene.json" in capsys.readouterr().err


def test_synth_cli_people_in_a_room_preset(tmp_path, capsys):
    out = tmp_path / "hd4"
    args = ["synth", "--preset", "hd4", "--out", str(out), "--frames", "3", "--size", "96x54"]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["num_cameras"] == 4 and report["background_frames"] == 0
    assert report["image_size"] == [96, 54]
    # Three frames: only the seated actor's stretch falls inside (the others are clipped away).
    assert report["stretches"]["seated"] == [{"actor": 3, "start": 0, "stop": 3}]
    assert report["stretches"]["still"] == [] and report["stretches"]["dimming"] == []
    gt = GroundTruth.open(out)
    assert gt.stretches == report["stretches"] and gt.illumination(2) == 1.0
    assert gt.seated_from_start == [3]
    assert not (out / "background").exists()
    # The table form lists the stretches.
    assert main([*args, "--overwrite"]) == 0
    text = capsys.readouterr().out
    assert "stretches" in text and "seated" in text


def test_synth_cli_small_object_preset(tmp_path, capsys):
    out = tmp_path / "object"
    args = ["synth", "--preset", "object", "--out", str(out), "--num-frames", "1"]
    args += ["--size", "200x150"]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["num_cameras"] == 12 and report["image_size"] == [200, 150]
    gt = GroundTruth.open(out)
    cloud = gt.reference_cloud(0, part="all", min_views=1)
    P = cloud.points3D
    # The table top 6 cm under the target, the object on it (~13 cm tall, within 9 cm of the
    # target horizontally), sampled finely (0.5 mm voxels).
    on_table = np.abs(P[:, 2] - 0.74) < 0.001
    obj = (P[:, 2] > 0.742) & (np.linalg.norm(P[:, :2], axis=1) < 0.09)
    assert on_table.sum() > 1000 and obj.sum() > 1000
    assert P[obj, 2].max() > 0.86
    kinds = {
        f["kind"] for f in json.loads((out / "gt" / "scene.json").read_text())["scene"]["furniture"]
    }
    assert kinds == {"box", "cylinder", "ellipsoid"}
    # Scored against its own truth at 0.1 % of the camera distance (~0.6 mm).
    pred = tmp_path / "pred.ply"
    write_ply(pred, cloud)
    argv = ["evaluate", str(pred), "--gt", str(out), "--part", "all", "--time", "0"]
    assert main([*argv, "-d", "0.1%", "--json"]) == 0
    text = capsys.readouterr().out
    assert text.count('"precision": 1.0') >= 1 and text.count('"recall": 1.0') >= 1, text


def test_synth_cli_site_preset(tmp_path, capsys):
    """A site's scale: five cameras 14 m from the yard's centre, people from the first frame."""
    out = tmp_path / "site"
    args = ["synth", "--preset", "site", "--out", str(out), "--frames", "2", "--size", "192x108"]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["num_cameras"] == 5 and report["background_frames"] == 0
    gt = GroundTruth.open(out)
    fg = gt.reference_cloud(1, part="foreground", min_views=2)
    assert len(fg) > 0 and float(fg.points3D[:, 2].max()) < 2.2  # people, on the ground
    centres = gt.rig.centers
    assert 12.0 < float(np.median(np.linalg.norm(centres[:, :2], axis=1))) < 16.0
