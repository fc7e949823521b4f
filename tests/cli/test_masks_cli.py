"""``edgerecon masks`` on a small generated dataset with ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgerecon.cli import main


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from edgerecon.synth import preset_config, write_dataset

    out = tmp_path_factory.mktemp("masks_cli") / "scene"
    config = preset_config(
        "demo", width=320, height=240, num_frames=6, background_frames=10, seed=3
    )
    write_dataset(config, out)
    return out


def test_masks_cli_writes_masks_and_scores(scene_dir: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "masks"
    rc = main(["masks", "--dataset", str(scene_dir), "--time", "5", "--out", str(out), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["background_model"] == "background clip"
    assert summary["time"] == 5
    cams = summary["cameras"]
    assert len(cams) == 5
    for c in cams:
        mask = cv2.imread(str(out / f"{c['camera']}_mask.png"), cv2.IMREAD_GRAYSCALE)
        assert mask.shape == (240, 320)
        assert set(np.unique(mask)) <= {0, 255}
        assert int((mask > 0).sum()) == c["area_px"]
        assert (out / f"{c['camera']}_overlay.png").is_file()
        assert c["num_objects"] == len(c["objects"])
        # With a background clip nothing is unsettled: the hull fill adds nothing.
        assert c["filled_by_hull_px"] == 0 and c["removed_by_hull_px"] >= 0
    # Masks match the ground truth of the synthetic scene.
    ious = [c["iou_vs_ground_truth"] for c in cams]
    # 320x240 is a hard, low-resolution case (native demo resolution: see tests/scene).
    assert np.mean(ious) > 0.75, ious
    assert json.loads((out / "masks.json").read_text())["cameras"] == cams
    assert summary["hull"]["status"] == "ok" and summary["hull"]["num_objects"] >= 1


def test_masks_cli_table_and_hull_ply(scene_dir: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from edgerecon.io.ply import read_ply

    out = tmp_path / "m"
    rc = main(["masks", "--dataset", str(scene_dir), "-t", "2", "-o", str(out), "--hull-ply"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "IoU vs GT" in text and "cam0" in text and "visual hull" in text
    assert "hull-filled px" in text
    cloud = read_ply(out / "hull.ply")
    assert len(cloud) > 100 and cloud.labels is not None and cloud.labels.min() >= 1


def test_masks_cli_bad_time_is_a_clean_error(scene_dir: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    rc = main(["masks", "--dataset", str(scene_dir), "--time", "99", "--out", str(tmp_path)])
    assert rc == 2
    assert "--time 99" in capsys.readouterr().err
