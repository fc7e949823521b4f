"""One definition of the background models over a stream (scene/stream.py): the schedule,
and the same masks for a time index whatever the order of the tasks before it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.io.dataset import open_dataset
from edgerecon.scene.foreground import ForegroundConfig
from edgerecon.scene.stream import (
    bootstrap_indices,
    bootstrap_scene,
    dataset_scene_at,
    update_step,
)
from edgerecon.types import DataError


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small people-in-a-room stream without an empty-scene clip (hd4 at 192x108)."""
    from edgerecon.synth import preset_config, write_dataset

    out = tmp_path_factory.mktemp("room") / "scene"
    write_dataset(preset_config("hd4", width=192, height=108, num_frames=40), out)
    return out


def test_schedule_known_answers() -> None:
    cfg = ForegroundConfig()
    assert update_step(25.0, cfg) == 12  # one update per 0.5 s
    assert update_step(6.0, cfg) == 3
    assert update_step(None, cfg) == 12  # unknown rate: 25 fps assumed
    assert bootstrap_indices(100, 25.0, cfg) == [0, 3, 7, 10, 14, 17, 21, 24]
    assert bootstrap_indices(3, 25.0, cfg) == [0, 1, 2]  # a short stream: all of it
    with pytest.raises(ValueError, match="update_interval_s"):
        ForegroundConfig(update_interval_s=0)


def test_a_live_stream_s_bootstrap_frames_spread_over_its_first_second(room: Path) -> None:
    """A live reader gives the next fresh set whatever index it is asked for: the bootstrap
    reads every set of its span and keeps those of ``bootstrap_indices``, so that they lie
    as far apart in the stream as a recording's (eight reads in a row would be eight
    consecutive frames); a recorded reader is read at those indices only."""
    from edgerecon.io.streams import LIVE_FRAMES
    from edgerecon.scene.stream import read_spread

    ds = open_dataset(room)
    with ds.open_frames() as recorded:

        class Live:
            """Frames as a live stream gives them: in order, whatever ``t``."""

            num_frames = LIVE_FRAMES

            def __init__(self) -> None:
                self.next = 0

            def read(self, t: int):
                frames = recorded.read(self.next)
                self.next += 1
                return frames

        indices = bootstrap_indices(LIVE_FRAMES, ds.fps, ForegroundConfig())
        assert len(indices) == 8 and indices[-1] > 8
        live = Live()
        sets = list(read_spread(live, indices))
        assert [fs.time_index for fs in sets] == indices  # the n-th fresh set is frame n
        assert live.next == indices[-1] + 1
        assert [fs.time_index for fs in read_spread(recorded, indices)] == indices

        class Broken:
            """A recording whose frame set 3 does not decode."""

            num_frames = recorded.num_frames

            def read(self, t: int):
                if t == 3:
                    raise DataError("frame 3 does not decode")
                return recorded.read(t)

        told: list[int] = []
        kept = read_spread(Broken(), indices, on_error=lambda t, exc: told.append(t))
        assert [fs.time_index for fs in kept] == [i for i in indices if i != 3] and told == [3]
        with pytest.raises(DataError, match="does not decode"):
            list(read_spread(Broken(), indices))
        # The bootstrap: the same models from the live reader as from the recording.
        spread = bootstrap_scene(ds.rig, Live(), ds.fps)
        stored = bootstrap_scene(ds.rig, recorded, ds.fps)
    for a, b in zip(spread.foreground.models, stored.foreground.models, strict=True):
        assert np.array_equal(a.state.mean, b.state.mean)


def test_the_masks_of_a_time_index_do_not_depend_on_the_tasks_before_it(room: Path) -> None:
    """The online front-end's pattern (pending updates, segment, the task frame's own update
    after the critical path) gives the masks of a fresh ``dataset_scene_at`` at every task."""
    ds = open_dataset(room)
    with ds.open_frames() as source:
        live = bootstrap_scene(ds.rig, source, ds.fps)
        assert live.step == 12 and live.learned_from.startswith("median of 8 frames")
        for t in (5, 13, 24, 31, 38):  # tasks at an irregular rate, 24 on the schedule
            for s in live.pending(t):
                live.learn(source.read(s))
            frames = source.read(t)
            result = live.segment(frames)
            live.learn(frames, result)
            fresh = dataset_scene_at(ds, t).segment(frames)
            for a, b in zip(result.masks, fresh.masks, strict=True):
                assert a is not None and b is not None
                np.testing.assert_array_equal(a, b)
        assert live.updates == 4  # 0, 12, 24, 36
    assert live.next_update == 48


def test_masks_and_reconstruct_split_see_the_same_foreground(
    room: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["masks", "--dataset", str(room), "--time", "30", "-o", str(tmp_path / "m")]) == 0
    rc = main(
        ["reconstruct", "--dataset", str(room), "--time", "30", "--split", "--out",
         str(tmp_path / "r"), "--scale", "0.5"]
    )  # fmt: skip
    assert rc == 0
    capsys.readouterr()
    masks = json.loads((tmp_path / "m" / "masks.json").read_text())
    split = json.loads((tmp_path / "r" / "timings.json").read_text())
    from_masks = [c["area_fraction"] for c in masks["cameras"]]
    assert split["foreground_area"] == pytest.approx(from_masks, abs=1e-9)
    assert masks["background_updates"] == split["background_updates"] == 3  # 0, 12, 24
    assert masks["static_scene_from"] is split["static_scene_from"] is None  # check off


def test_the_static_scene_is_the_streams_own(room: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ghost check's static scene comes from frames on the schedule, so the online
    pattern and a fresh catch-up (which builds only the latest one) agree to the pixel; a
    static scene that fails keeps the previous one."""
    from edgerecon.scene import stream
    from edgerecon.scene.ghosts import StaticCheckConfig

    cfg = ForegroundConfig(static_check=True, static=StaticCheckConfig(every_s=0.5, keep=2))
    assert stream.static_step(25.0, cfg) == 12
    on = ForegroundConfig(static_check=True)
    assert stream.static_step(25.0, on) == 48  # 2 s, on the update schedule
    assert stream.static_step(25.0, ForegroundConfig()) == 0  # off by default
    ds = open_dataset(room)
    built: list[int] = []
    real = stream.reconstruct_static

    def counting(frames, rig, masks):  # type: ignore[no-untyped-def]
        built.append(frames.time_index)
        return real(frames, rig, masks)

    monkeypatch.setattr(stream, "reconstruct_static", counting)
    with ds.open_frames() as source:
        live = bootstrap_scene(ds.rig, source, ds.fps, cfg)
        for t in (5, 13, 31):
            for s in live.pending(t):
                live.learn(source.read(s))
            frames = source.read(t)
            result = live.segment(frames)
            live.learn(frames, result)
        assert built == [0, 12, 24] and live.static_from == 24
        assert live.foreground.static_depth is not None
        built.clear()
        fresh = stream.scene_at(ds.rig, source, ds.fps, 31, cfg)
        assert built == [12, 24] and fresh.static_from == 24  # the latest `keep`
        assert len(live.foreground.static_clouds) == len(fresh.foreground.static_clouds) == 2
        for a, b in zip(live.foreground.static_clouds, fresh.foreground.static_clouds, strict=True):
            np.testing.assert_array_equal(a, b)
        frames = source.read(31)
        for a, b in zip(live.segment(frames).masks, fresh.segment(frames).masks, strict=True):
            assert a is not None and b is not None
            np.testing.assert_array_equal(a, b)

        # The front-end keeps a static scene due on a frame that was not a task for after
        # the task's critical path: the task still sees the previous one.
        built.clear()
        for s in live.pending(40):
            live.learn(source.read(s), defer_static=True)
        assert live.static_from == 24 and built == []
        assert live.settle() > 0 and live.static_from == 36 and built == [36]
        assert live.settle() == 0.0
        # Several kept ones (a task after a long gap): the last `keep` are built, in order,
        # as a catch-up builds them.
        late = bootstrap_scene(ds.rig, source, ds.fps, cfg)
        built.clear()
        for s in late.pending(31):
            late.learn(source.read(s), defer_static=True)
        assert built == [] and late.settle() > 0 and built == [12, 24]
        for a, b in zip(late.foreground.static_clouds, fresh.foreground.static_clouds, strict=True):
            np.testing.assert_array_equal(a, b)
        built.clear()

        def broken(frames, rig, masks):  # type: ignore[no-untyped-def]
            raise RuntimeError("no texture")

        monkeypatch.setattr(stream, "reconstruct_static", broken)
        points = fresh.foreground.static_clouds
        fresh.learn(source.read(36))
        assert fresh.next_update == 48  # the update itself went through
        assert fresh.static_from == 24 and fresh.foreground.static_clouds is points


def test_a_static_scene_without_one_camera(room: Path) -> None:
    """A frame set that lacks a camera still gives a static scene (from the others), and the
    masks are checked against it."""
    import dataclasses

    from edgerecon.scene import stream
    from edgerecon.scene.ghosts import StaticCheckConfig

    cfg = ForegroundConfig(static_check=True, static=StaticCheckConfig(every_s=0.5))
    ds = open_dataset(room)
    with ds.open_frames() as source:
        tracker = bootstrap_scene(ds.rig, source, ds.fps, cfg)
        frames = source.read(0)
        gap = dataclasses.replace(frames, images=(frames.images[0], None, *frames.images[2:]))
        tracker.learn(gap)
        assert tracker.static_from == 0 and len(tracker.foreground.static_clouds) == 1
        assert stream.static_step(ds.fps, cfg) == tracker.static_step == 12
        result = tracker.segment(source.read(5))
        assert "static_check" in result.timings.to_dict()
