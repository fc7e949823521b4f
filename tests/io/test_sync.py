"""Synchronisation offsets from what the cameras see move: GCC-PHAT lags, the solve over
pairs, joint evidence, and ``import --offset auto`` on videos of cameras started apart."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.io import VideoFrameSource, open_dataset
from edgerecon.io.calibration import save_rig
from edgerecon.io.importer import parse_offsets
from edgerecon.io.sync import PairLag, _join_unlinked, _solve, best_lag, estimate_offsets
from tests.conftest import ring_rig

W, H = 64, 48


def _bursts(n: int, seed: int = 0) -> np.ndarray:
    """A motion signal: quiet, with bursts at random moments (people moving now and then)."""
    rng = np.random.default_rng(seed)
    s = 0.2 * rng.random(n)
    for start in rng.choice(n - 10, size=n // 25, replace=False):
        s[start : start + rng.integers(3, 10)] += rng.uniform(1, 4)
    return s


def test_best_lag_finds_the_shift_of_another_cameras_view():
    s = _bursts(600)
    # b sees the same moments 17 samples later, weighted differently, with someone only it
    # sees moving too, and noisier.
    b = 3.0 * np.roll(s, 17) + _bursts(600, seed=9)
    b += 0.05 * np.random.default_rng(1).standard_normal(len(b))
    lag, peak, second = best_lag(s, b, max_lag=100)
    assert lag == -17 and peak > 8 and peak - second > 3
    lag, *_ = best_lag(b, s, max_lag=100)
    assert lag == 17


def test_cameras_that_see_different_motion_are_not_confident():
    # Nothing moves in view of both: no lag should be claimed.
    for seed in range(5):
        _, peak, second = best_lag(_bursts(600, seed), _bursts(600, seed + 100), max_lag=100)
        assert peak < 4.0 or peak - second < 1.5, (seed, peak, second)


def _pair(a, b, lag, peak=10.0, second=2.0):
    return PairLag(a=a, b=b, lag=lag, peak=peak, second=second, confident=peak - second >= 1.5)


def test_solve_drops_a_pair_that_disagrees_and_names_unlinked_cameras():
    names = ["a", "b", "c", "d", "e"]
    # Truth: a 0, b -4, c 3, d 0; one confident wrong pair a-d; e linked by nothing.
    pairs = [
        _pair("a", "b", 4),
        _pair("a", "c", -3),
        _pair("b", "c", -7),
        _pair("a", "d", 25, peak=6.0),
        _pair("b", "d", -4),
        _pair("c", "d", 3),
        _pair("a", "e", 40, peak=3.0, second=2.9),
    ]
    lags, unlinked, used = _solve(names, pairs)
    assert lags["b"] - lags["a"] == -4 and lags["c"] - lags["a"] == 3
    assert lags["d"] - lags["a"] == 0
    assert unlinked == ["e"] and 3 not in used and 6 not in used


def test_an_unlinked_camera_is_matched_against_the_linked_ones_consensus():
    from edgerecon.io.sync import SyncConfig

    rng = np.random.default_rng(6)
    s = _bursts(700, seed=3)
    # Linked cameras a, b, c (offsets 0, 4, 9: camera x's frame t + o_x shows common time t).
    lags = {"a": 0, "b": 4, "c": 9}
    signals = {
        n: np.roll(s, o)[:600] * (1 + k) + 0.3 * rng.standard_normal(600)
        for k, (n, o) in enumerate(lags.items())
    }
    # w sees the same motion faintly (offset 6) under heavy noise of its own.
    signals["w"] = 0.35 * np.roll(s, 6)[:600] + 0.8 * rng.standard_normal(600)
    got, still, tried = _join_unlinked(signals, {**lags, "w": 0}, ["w"], 100, SyncConfig())
    assert still == [] and got["w"] == 6, tried
    # A camera that saw none of it stays unlinked.
    signals["w"] = _bursts(600, seed=77)
    got, still, _ = _join_unlinked(signals, {**lags, "w": 0}, ["w"], 100, SyncConfig())
    assert still == ["w"] and got["w"] == 0


def _videos(tmp_path, starts: dict[str, int], n: int = 240, fps: float = 25.0):
    """Videos of one blob moving in bursts, seen by each camera from its own side (mirrored,
    scaled, coloured), each camera started ``starts[name]`` frames late."""
    rng = np.random.default_rng(4)
    speed = _bursts(n + max(starts.values()), seed=2)
    pos = np.cumsum(speed)
    paths = {}
    for k, (name, start) in enumerate(starts.items()):
        writer = cv2.VideoWriter(
            str(tmp_path / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H)
        )
        background = rng.integers(40, 90, (H, W, 3)).astype(np.uint8)
        for t in range(start, start + n):
            frame = background.copy()
            x = (pos[t] * (1.5 + 0.5 * k)) % (W - 10)
            x = W - 10 - x if k % 2 else x
            y = 10 + 6 * k
            cv2.circle(frame, (int(x) + 5, y), 4 + k, (200, 180 - 30 * k, 60 + 40 * k), -1)
            writer.write(frame)
        writer.release()
        paths[name] = tmp_path / f"{name}.avi"
    return paths


def test_estimate_offsets_of_cameras_started_apart(tmp_path):
    starts = {"cam0": 0, "cam1": 7, "cam2": 3, "cam3": 12}
    paths = _videos(tmp_path, starts)
    with VideoFrameSource(paths) as src:
        result = estimate_offsets(src)
    # cam3 started last: its frame t is the others' frame t + 12 - start.
    assert result.offsets == {"cam0": 12, "cam1": 5, "cam2": 9, "cam3": 0}, result.pairs
    assert result.ok and all(p.confident for p in result.pairs)


def _started_apart(tmp_path):
    """A rig's calibration and three cameras' videos started 4, 0 and 9 frames late: (rig,
    import arguments without --out, the offsets that synchronise them)."""
    starts = {"cam0": 4, "cam1": 0, "cam2": 9}
    paths = _videos(tmp_path, starts)
    rig = ring_rig(3, width=W, height_px=H, focal_px=40.0)
    save_rig(tmp_path / "rig.json", rig)
    sources = [f"{n}={paths[c]}" for n, c in zip(rig.names, starts, strict=True)]
    want = dict(zip(rig.names, (5, 9, 0), strict=True))
    return rig, ["import", str(tmp_path / "rig.json"), *sources], want


def test_import_offset_auto(tmp_path, capsys):
    _, args, want = _started_apart(tmp_path)
    out = tmp_path / "ds"
    args = [*args, "--offset", "auto", "--out", str(out)]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert {c["name"]: c["offset"] for c in report["cameras"]} == want
    assert report["sync"]["offsets"] == want
    assert any("offsets estimated from the cameras' motion" in n for n in report["notes"])
    assert dict(open_dataset(out).frames.offsets) == {k: v for k, v in want.items() if v}
    assert parse_offsets(["auto"]) == "auto" and parse_offsets(["a=2,b=3"]) == {"a": 2, "b": 3}
    with pytest.raises(ValueError, match="CAMERA=FRAMES"):
        parse_offsets(["auto,cam0=2"])


def test_sync_command_checks_and_writes_a_datasets_offsets(tmp_path, capsys):
    rig, args, want = _started_apart(tmp_path)
    out = tmp_path / "ds"
    assert main([*args, "-o", str(out), "-q"]) == 0
    capsys.readouterr()
    assert main(["sync", "--dataset", str(out), "--json"]) == 3  # out of sync
    report = json.loads(capsys.readouterr().out)
    assert report["new"] == want and sorted(report["out_of_sync"]) == sorted(rig.names[:2])
    assert main(["sync", "--dataset", str(out), "--write", "--json"]) == 0
    capsys.readouterr()
    assert dict(open_dataset(out).frames.offsets) == {k: v for k, v in want.items() if v}
    assert main(["sync", "--dataset", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["out_of_sync"] == [] and set(report["change"].values()) == {0}


def test_two_groups_linked_apart_are_not_one_clock():
    # a-b and c-d-e agree among themselves, nothing links the groups: the larger group is
    # the linked one, the other's cameras are not claimed.
    names = ["a", "b", "c", "d", "e"]
    pairs = [_pair("a", "b", 3), _pair("c", "d", -2), _pair("d", "e", 5), _pair("c", "e", 3)]
    lags, unlinked, used = _solve(names, pairs)
    assert sorted(unlinked) == ["a", "b"] and used == {1, 2, 3}
    assert lags["c"] - lags["d"] == -2 and lags["d"] - lags["e"] == 5
    assert lags["a"] == lags["b"] == 0
