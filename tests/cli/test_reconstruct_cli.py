import json

from edgerecon.cli import main
from edgerecon.io.ply import read_ply


def test_reconstruct_writes_clouds_and_timings(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "rec"
    code = main(
        [
            "reconstruct",
            "--dataset",
            str(tiny_dataset),
            "--time",
            "3",
            "--scale",
            "0.8",
            "--cameras",
            "0,1,3,4",
            "--out",
            str(out),
            "--json",
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["camera_ids"] == [0, 1, 3, 4] and summary["scale"] == 0.8
    assert summary["num_dense_points"] == len(read_ply(out / "dense.ply")) > 0
    assert summary["num_sparse_points"] == len(read_ply(out / "sparse.ply")) > 0
    # Every cloud says which points are inferred (ground completion: none on this floor).
    assert summary["num_inferred_points"] == read_ply(out / "dense.ply").num_inferred
    assert "inferred" in read_ply(out / "dense.ply").attributes
    timings = json.loads((out / "timings.json").read_text())
    assert timings["seconds"]["dense.depth"] > 0


def test_reconstruct_split_writes_merged_parts(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "split"
    assert (
        main(
            [
                "reconstruct",
                "--dataset",
                str(tiny_dataset),
                "--time",
                "5",
                "--split",
                "--out",
                str(out),
                "--json",
            ]
        )
        == 0
    )
    summary = json.loads(capsys.readouterr().out)
    merged = read_ply(out / "merged.ply")
    assert len(merged) == summary["num_merged_points"]
    assert len(read_ply(out / "fg.ply")) + len(read_ply(out / "bg.ply")) == len(merged)
    assert summary["num_foreground_points"] > 0
    for name in ("merged", "fg", "bg"):
        assert "inferred" in read_ply(out / f"{name}.ply").attributes
    assert summary["num_inferred_points"] == merged.num_inferred


def test_reconstruct_rejects_bad_camera_and_scale(tiny_dataset, tmp_path, capsys):
    assert (
        main(
            [
                "reconstruct",
                "--dataset",
                str(tiny_dataset),
                "--cameras",
                "0,9,1",
                "--out",
                str(tmp_path),
            ]
        )
        == 2
    )
    assert "camera" in capsys.readouterr().err
    assert (
        main(
            [
                "reconstruct",
                "--dataset",
                str(tiny_dataset),
                "--scale",
                "1.5",
                "--out",
                str(tmp_path),
            ]
        )
        == 2
    )
    assert "scale" in capsys.readouterr().err
    assert (
        main(
            ["reconstruct", "--dataset", str(tiny_dataset), "--time", "99", "--out", str(tmp_path)]
        )
        == 2
    )
