"""Shared fixtures of the runtime tests: the tiny dataset with its scene model, and a
runtime configuration with generous waits (a busy 2-core machine) and background updates on
at half scale (recovery is tested with everything on)."""

from __future__ import annotations

import time

import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online
from edgerecon.runtime.engine import learn_scene_model


@pytest.fixture(scope="session")
def tiny(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, learn_scene_model(ds)


def runtime_config(**kw):
    kw.setdefault("deadline_s", 20.0)
    kw.setdefault("golden_timeout_s", 20.0)
    kw.setdefault("background_scale", 0.5)
    return RuntimeConfig(**kw)


def run_frames(tiny, out, start, stop, config=None, **kw):
    """``run_online`` on the tiny dataset over ``start:stop`` (options in ``kw``: those of
    ``SessionOptions`` and of ``run_online``)."""
    ds, scene = tiny
    names = set(SessionOptions.__dataclass_fields__)
    opts = SessionOptions(
        frames=FrameRange(start=start, stop=stop), **{k: v for k, v in kw.items() if k in names}
    )
    rest = {k: v for k, v in kw.items() if k not in names}
    rest.setdefault("scene", scene)
    return run_online(ds, config or runtime_config(), opts, out, **rest)


def wait_until(predicate, timeout=120.0):
    """Whether ``predicate()`` became true within ``timeout`` seconds (polled)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return False
