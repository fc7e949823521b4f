"""``edgerecon info`` on a synthetic dataset (known answers) and on utrecht4cam."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.cli.info import baseline_angles_deg, convergence_point
from edgerecon.io import write_dataset_descriptor
from edgerecon.scene.people import PERSON_MODEL_FILE
from tests.conftest import ring_rig, shared_data


def _tiny_dataset(root, num_cameras=4):
    rig = ring_rig(num_cameras, width=32, height_px=24, focal_px=30.0)
    cams = {}
    for cam in rig:
        for t in range(3):
            path = root / "frames" / cam.name / f"{t:04d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), np.zeros((24, 32, 3), np.uint8))
        cams[cam.name] = f"frames/{cam.name}/{{index:04d}}.png"
    (root / "gt").mkdir()
    write_dataset_descriptor(
        root,
        rig=rig,
        frames={"kind": "images", "cameras": cams},
        name="tiny",
        fps=5.0,
        ground_truth="gt",
    )
    return rig


def test_baseline_angles_known_answer():
    # Four cameras on a ring looking at (0, 0, 1) from height 1.5, radius 4: neighbours are
    # 90 degrees apart around the ring; seen from the convergence point (0, 0, 1)...
    rig = ring_rig(4, radius=4.0, height=1.5)
    np.testing.assert_allclose(convergence_point(rig), [0, 0, 1.0], atol=1e-9)
    angles = baseline_angles_deg(rig)
    d = np.array([4.0, 0.0, 0.5]) / np.hypot(4.0, 0.5)
    opposite = np.degrees(np.arccos(-(d[0] ** 2) + d[2] ** 2))
    neighbour = np.degrees(np.arccos(d[2] ** 2))
    np.testing.assert_allclose(angles[0], [0, neighbour, opposite, neighbour], atol=1e-9)
    np.testing.assert_allclose(angles, angles.T)


def test_info_json_on_synthetic_dataset(tmp_path, capsys):
    rig = _tiny_dataset(tmp_path)
    assert main(["info", "--dataset", str(tmp_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["name"] == "tiny" and info["num_cameras"] == 4 and info["num_frames"] == 3
    assert info["fps"] == 5.0 and info["duration_s"] == pytest.approx(0.6)
    assert info["unit"] == "m" and info["background"] is False
    assert info["ground_truth"].endswith("gt")
    cam = info["cameras"][2]
    assert cam["name"] == "cam2" and (cam["width"], cam["height"]) == (32, 24)
    assert cam["fx"] == 30.0 and cam["cx"] == 15.5
    np.testing.assert_allclose(cam["center"], rig[2].center)
    np.testing.assert_allclose(info["baseline_angles_deg"], baseline_angles_deg(rig), atol=1e-3)


def test_info_says_whether_the_person_model_serves(tmp_path, capsys, monkeypatch):
    _tiny_dataset(tmp_path / "ds")  # no clip of the empty scene
    monkeypatch.setenv("EDGERECON_MODELS", str(tmp_path / "models"))
    assert main(["info", "--dataset", str(tmp_path / "ds"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["person_model"].startswith("not fetched")
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / PERSON_MODEL_FILE).write_bytes(b"a truncated download")
    assert main(["info", "--dataset", str(tmp_path / "ds")]) == 0
    assert "person model: left out" in capsys.readouterr().out


def test_info_table_and_clean_errors(tmp_path, capsys):
    _tiny_dataset(tmp_path)
    assert main(["info", "--dataset", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "tiny" in out and "baseline angles" in out and "cam3" in out
    assert "ground truth:" in out and "distortion: none" in out
    assert main(["info", "--dataset", str(tmp_path / "missing")]) == 2
    assert "dataset not found" in capsys.readouterr().err
    (tmp_path / "frames" / "cam1" / "0000.png").unlink()
    for f in (tmp_path / "frames" / "cam1").iterdir():
        f.unlink()
    assert main(["info", "--dataset", str(tmp_path)]) == 2
    assert "cam1" in capsys.readouterr().err


def test_info_utrecht(capsys):
    root = shared_data("utrecht4cam")
    assert main(["info", "--dataset", str(root), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["layout"] == "utrecht4cam" and info["unit"] == "mm"
    assert info["num_frames"] == 426 and info["fps"] == 50.0
    assert info["background_frames"] == 132
    angles = np.array(info["baseline_angles_deg"])
    # Cameras in the room's corners: wide baselines, 44 to 144 degrees apart.
    off = angles[~np.eye(4, dtype=bool)]
    assert off.min() > 40 and off.max() < 150
    # 644x486 frames densified at full resolution: nothing finer than r = 1; the sweep's
    # level drops to a coarser one at r ~0.56, where r 0.45-0.56 cost more.
    scales = info["image_scales"]
    assert (scales["min"], scales["golden"], scales["finest"]) == (0.3, 1.0, 1.0)
    ((a, b),) = scales["skipped"]
    assert 0.4 < a < 0.5 < 0.56 < b < 0.6
    assert main(["info", "--dataset", str(root)]) == 0
    assert f"skipped, where a larger r costs less: {a:g}-{b:g}" in capsys.readouterr().out


def test_info_check_reports_every_unusable_frame(tmp_path, capsys):
    rig = ring_rig(4, width=32, height_px=24, focal_px=30.0)
    rng = np.random.default_rng(1)
    cams = {}
    for cam in rig:
        for t in range(4):
            path = tmp_path / "frames" / cam.name / f"{t:04d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))
        cams[cam.name] = f"frames/{cam.name}/{{index:04d}}.png"
    write_dataset_descriptor(tmp_path, rig=rig, frames={"kind": "images", "cameras": cams})
    frames = tmp_path / "frames"
    assert main(["info", "--dataset", str(tmp_path), "--check", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["check"]["num_unusable"] == 0
    (frames / "cam0" / "0001.png").write_bytes(b"")  # zero bytes
    data = (frames / "cam1" / "0002.png").read_bytes()
    (frames / "cam1" / "0002.png").write_bytes(data[: len(data) // 3])  # truncated
    cv2.imwrite(str(frames / "cam2" / "0002.png"), np.zeros((12, 16, 3), np.uint8))  # size
    (frames / "cam3" / "0001.png").unlink()  # missing
    cv2.imwrite(str(frames / "cam3" / "0003.png"), np.zeros((24, 32, 3), np.uint8))  # black
    cv2.imwrite(str(frames / "cam0" / "0003.png"), np.full((24, 32, 3), 255, np.uint8))
    assert main(["info", "--dataset", str(tmp_path), "--check", "--json"]) == 3
    check = json.loads(capsys.readouterr().out)["check"]
    found = {(cam, p["time"]): p["problem"] for cam, ps in check["unusable"].items() for p in ps}
    assert set(found) == {
        ("cam0", 1),
        ("cam1", 2),
        ("cam2", 2),
        ("cam3", 1),
        ("cam3", 3),
        ("cam0", 3),
    }
    assert "cannot be decoded" in found["cam0", 1] and "cannot be decoded" in found["cam1", 2]
    assert "16x12" in found["cam2", 2] and "missing" in found["cam3", 1]
    assert found["cam3", 3] == "black" and found["cam0", 3] == "saturated"
    # Times 0 keeps 4 cameras, 1 keeps 2, 2 keeps 2, 3 keeps 2.
    assert check["usable_timestamps"] == 1
    assert main(["info", "--dataset", str(tmp_path), "--check"]) == 3
    out = capsys.readouterr().out
    assert "unusable frames" in out and "wrong size" in out and "6 unusable frames" in out


def test_info_check_reports_a_frozen_camera(tmp_path, capsys):
    # 2 fps: cam1 repeats its frame of time 2 at times 3-6 (2 s of the stream), cam2 from
    # time 5 to the end (1.5 s: not long enough).
    rig = ring_rig(4, width=32, height_px=24, focal_px=30.0)
    rng = np.random.default_rng(2)
    cams = {}
    for cam in rig:
        images = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(8)]
        for t in range(8):
            held = (cam.name == "cam1" and 3 <= t <= 6) or (cam.name == "cam2" and t >= 5)
            path = tmp_path / "frames" / cam.name / f"{t:04d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), images[(2 if cam.name == "cam1" else 4) if held else t])
        cams[cam.name] = f"frames/{cam.name}/{{index:04d}}.png"
    write_dataset_descriptor(tmp_path, rig=rig, frames={"kind": "images", "cameras": cams}, fps=2.0)
    assert main(["info", "--dataset", str(tmp_path), "--check", "--json"]) == 0  # usable
    check = json.loads(capsys.readouterr().out)["check"]
    assert check["frozen"] == {"cam1": [{"from": 2, "to": 7}]}
    assert main(["info", "--dataset", str(tmp_path), "--check"]) == 0
    assert "camera cam1: the same frame while the others' changed at times 2-6" in (
        capsys.readouterr().out
    )


def test_info_check_reports_a_camera_whose_view_moved(tmp_path, capsys):
    """cam2 turned 1.5 degrees (tilted) from time 3 of 8: ``moved`` dates it at time 3."""
    from tests.quality.test_frames import _texture, _turned

    rig = ring_rig(3, width=480, height_px=360, focal_px=400.0)
    rng = np.random.default_rng(5)
    cams = {}
    for cam in rig:
        room = _texture(rng, 360, 480)
        for t in range(8):
            image = _turned(room, 1.5, (1.0, 0.0, 0.0)) if cam.name == "cam2" and t >= 3 else room
            noisy = np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)
            path = tmp_path / "frames" / cam.name / f"{t:04d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), noisy)
        cams[cam.name] = f"frames/{cam.name}/{{index:04d}}.png"
    write_dataset_descriptor(tmp_path, rig=rig, frames={"kind": "images", "cameras": cams}, fps=2.0)
    main(["info", "--dataset", str(tmp_path), "--check", "--json"])
    (move,) = json.loads(capsys.readouterr().out)["check"]["moved"]
    assert move["camera"] == "cam2" and move["time"] == 3
    assert move["shift_px"][1] == pytest.approx(-400 * np.tan(np.radians(1.5)), abs=1.0)
    main(["info", "--dataset", str(tmp_path), "--check"])
    assert "camera cam2: its whole view moved at time 3" in capsys.readouterr().out
