"""Scene descriptions: configs, rig presets and the deterministic scene builder.

A ``SceneConfig`` (frozen, validated) says what to generate; ``build_scene(config)`` turns it
into a ``SynthScene``: the rig (``edgerecon.geometry.Rig``), the static room with furniture,
the textures, the actors and the realism parameters (per-camera exposure, illumination over
time). Everything is derived from ``config.seed``: the same config gives the same scene, bit
for bit.

World frame: metres, z up, floor at z = 0, the room centred on the origin.

Presets (``preset_config(name, **overrides)``):

* ``ring``: N (default 8) cameras around the scene, 1280x720.
* ``arc7``: 7 cameras at 1920x1080, ~1720 px focal length, 15 degrees apart on an arc, looking
  at the scene centre, with Dance1-like barrel distortion (the paper's studio rig).
* ``demo``: 5 cameras at 640x480, 40 timestamps, 2 actors (the README's main job).
* ``object``: small-object capture: a carved object (millimetre relief, low-contrast faces)
  on a table, 12 cameras on a ring 0.55 m from it at 800x600, looking down at ~25 degrees;
  static (no actors), ground truth at 0.5 mm (see ``_object``).
* ``hd4`` / ``hd4p``: people in a room as real phone/webcam rigs film them: 4 cameras 90
  degrees apart at 1920x1080 (``hd4p``: 1080x1920, phones held upright), no background clip,
  250 frames at 25 fps of scripted actors (``ROOM_SCRIPTS``: one stands still for 6 s, one
  leaves and comes back, one sits talking) and a dimming light (``ROOM_LIGHTS``).
* ``site``: a first responders' rig outdoors, at a site's scale: 5 cameras at 1920x1080 on
  poles 4.5 m high, 14 m from the centre of a 44 x 44 m yard walled in, looking down at four
  people who walk there from the first frame (no background clip), scattered debris, the
  light dimming while a cloud passes (hd4's stretch).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig, look_at
from edgerecon.synth import motion
from edgerecon.synth.primitives import Box, Cylinder, Ellipsoid, Room
from edgerecon.synth.scripts import ROOM_LIGHTS, ROOM_SCRIPTS, ActorScript, scripted_path
from edgerecon.synth.textures import Texture, make_texture

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Largest texture side in texels (larger surfaces get coarser texels).
MAX_TEXTURE_SIDE = 2048
#: Dance1-like lens: OpenCV (k1, k2, p1, p2, k3) of a wide studio lens with barrel distortion.
STUDIO_DISTORTION = (-0.22, 0.27, 0.0, 0.0, -0.038)


def _check(cond: bool, name: str, value: Any, allowed: str) -> None:
    if not cond:
        raise ValueError(f"{name} = {value!r} is invalid: {allowed}")


@dataclass(frozen=True, kw_only=True)
class RigSpec:
    """How to place the cameras (generated from these parameters, deterministic)."""

    layout: Literal["ring", "arc"] = "ring"
    """'ring': evenly spaced all around the target; 'arc': ``spacing_deg`` apart on one side."""
    num_cameras: int = 8
    """Number of cameras N (>= 3)."""
    width: int = 1280
    """Image width, pixels."""
    height: int = 720
    """Image height, pixels."""
    focal_px: float = 1000.0
    """Focal length, pixels (square pixels)."""
    radius_m: float = 3.4
    """Horizontal distance of the cameras from the target, metres."""
    camera_height_m: float = 2.2
    """Mean camera height above the floor, metres."""
    target: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Point all cameras look at, metres."""
    spacing_deg: float = 15.0
    """Angle between neighbouring cameras on an arc (layout 'arc'), degrees."""
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """OpenCV distortion (k1, k2, p1, p2, k3) of every camera; zeros = ideal pinhole."""
    principal_offset_px: tuple[float, float] = (0.0, 0.0)
    """Principal point minus the image centre, pixels."""
    jitter_m: float = 0.1
    """Random perturbation of camera positions (and aim), metres; 0 = perfectly regular."""
    azimuth_deg: float | None = None
    """Ring layout: direction of the first camera from the target, degrees about z (0 = +x);
    None = a random rotation of the ring drawn from the seed."""

    def __post_init__(self) -> None:
        _check(self.layout in ("ring", "arc"), "layout", self.layout, "'ring' or 'arc'")
        _check(self.num_cameras >= 3, "num_cameras", self.num_cameras, "need >= 3")
        _check(16 <= self.width <= 8192, "width", self.width, "16..8192 pixels")
        _check(16 <= self.height <= 8192, "height", self.height, "16..8192 pixels")
        _check(self.focal_px > 0, "focal_px", self.focal_px, "must be > 0")
        _check(self.radius_m > 0.5, "radius_m", self.radius_m, "must be > 0.5 m")
        _check(0.3 < self.camera_height_m, "camera_height_m", self.camera_height_m, "> 0.3 m")
        _check(0 < self.spacing_deg < 180, "spacing_deg", self.spacing_deg, "in (0, 180)")
        _check(len(self.distortion) == 5, "distortion", self.distortion, "5 coefficients")
        _check(self.jitter_m >= 0, "jitter_m", self.jitter_m, "must be >= 0")


@dataclass(frozen=True, kw_only=True)
class RealismConfig:
    """Imaging effects, on at mild levels by default (0 turns each off)."""

    noise_sigma: float = 2.0
    """Standard deviation of additive Gaussian sensor noise, grey levels (0..255)."""
    exposure_spread: float = 0.04
    """Per-camera exposure gains are drawn from 1 +- this (relative)."""
    white_balance_spread: float = 0.02
    """Per-camera, per-channel colour gains are drawn from 1 +- this (relative)."""
    illumination_change: float = 0.0
    """Global light dims linearly by this fraction from the first background frame to the
    last frame (0 = constant light; e.g. 0.2 = 20 % darker at the end)."""
    blur_sigma_px: float = 0.5
    """Optical blur (Gaussian sigma, pixels) applied to every frame; 0 = none."""
    brightness: float = 1.0
    """Overall exposure scale."""
    contact_shadow: float = 0.4
    """Darkening of the floor under each actor (soft blob, view-independent, part of the
    background in the masks: as real shadows, it moves with the actor); 0 = none."""
    contact_shadow_radius_m: float = 0.8
    """Radius of the contact shadow on the floor (smooth fall-off to 0 there), metres."""
    light_keys: tuple[tuple[float, float], ...] = ()
    """A dimmer: (frame, level) keys, the global light level linear between them and held
    before the first and after the last (e.g. ((180, 1), (205, 0.45), (215, 0.45), (240, 1)):
    dims to 45 % over a second at 25 fps and recovers); multiplies ``illumination_change``;
    () = none."""

    def __post_init__(self) -> None:
        _check(self.noise_sigma >= 0, "noise_sigma", self.noise_sigma, "must be >= 0")
        _check(0 <= self.exposure_spread < 0.5, "exposure_spread", self.exposure_spread, "[0, 0.5)")
        _check(
            0 <= self.white_balance_spread < 0.5,
            "white_balance_spread",
            self.white_balance_spread,
            "[0, 0.5)",
        )
        _check(
            0 <= self.illumination_change < 0.9,
            "illumination_change",
            self.illumination_change,
            "[0, 0.9)",
        )
        _check(0 <= self.blur_sigma_px <= 5, "blur_sigma_px", self.blur_sigma_px, "[0, 5] px")
        _check(0 < self.brightness <= 4, "brightness", self.brightness, "(0, 4]")
        _check(0 <= self.contact_shadow < 1, "contact_shadow", self.contact_shadow, "[0, 1)")
        _check(
            self.contact_shadow_radius_m > 0,
            "contact_shadow_radius_m",
            self.contact_shadow_radius_m,
            "must be > 0",
        )
        keys = self.light_keys
        _check(
            all(len(k) == 2 and 0 < k[1] <= 2 for k in keys)
            and all(b[0] > a[0] for a, b in itertools.pairwise(keys)),
            "light_keys",
            keys,
            "(frame, level) pairs, frames increasing, levels in (0, 2]",
        )


@dataclass(frozen=True, kw_only=True)
class SceneConfig:
    """Everything that defines a synthetic sequence; ``build_scene`` is deterministic in it."""

    name: str = "synthetic"
    """Dataset name (written to dataset.json)."""
    rig: RigSpec = field(default_factory=RigSpec)
    """Camera placement and intrinsics."""
    num_frames: int = 40
    """Number of timestamps T."""
    num_actors: int = 2
    """Number of moving actors K (0 = empty scene)."""
    seed: int = 0
    """Seed of every random choice (layout, textures, paths, noise)."""
    fps: float = 25.0
    """Frame rate, frames per second (actors walk ~1 m/s)."""
    background_frames: int = 10
    """Frames of the empty scene before the sequence (the background-only clip); 0 = none."""
    room_size_m: tuple[float, float, float] = (8.0, 8.0, 3.0)
    """Room extent x, y, z (metres), centred on the origin, floor at z = 0."""
    num_furniture: int = 8
    """Boxes and cylinders standing around the capture area."""
    capture_radius_m: float = 1.8
    """Actors walk within this distance of the rig's target (horizontally), metres."""
    texel_m: float | None = None
    """Texture resolution, metres per texel; None = matched to the cameras' pixel footprint."""
    realism: RealismConfig = field(default_factory=RealismConfig)
    """Imaging effects."""
    gt_voxel_foreground_m: float = 0.003
    """Voxel size deduplicating the foreground ground-truth cloud, metres."""
    gt_voxel_background_m: float = 0.006
    """Voxel size deduplicating the background ground-truth cloud, metres."""
    actor_scripts: tuple[ActorScript, ...] = ()
    """Scripted motion of actors 1, 2, ... (keys, still intervals, presence, posture); actors
    beyond the scripts walk at random, scripts beyond ``num_actors`` are not used."""
    centerpiece: bool = False
    """Put a small carved object (~15 cm, relief of 2-4 mm, low-contrast faces) on a table
    under the rig's target (the ``object`` preset); the table top is at the target's height
    minus 6 cm."""

    def __post_init__(self) -> None:
        _check(bool(self.name), "name", self.name, "must be non-empty")
        _check(self.num_frames >= 1, "num_frames", self.num_frames, "need >= 1")
        _check(0 <= self.num_actors <= 20, "num_actors", self.num_actors, "0..20")
        _check(self.fps > 0, "fps", self.fps, "must be > 0")
        _check(self.background_frames >= 0, "background_frames", self.background_frames, ">= 0")
        _check(
            len(self.room_size_m) == 3 and min(self.room_size_m) >= 2.5,
            "room_size_m",
            self.room_size_m,
            "three sizes >= 2.5 m",
        )
        _check(0 <= self.num_furniture <= 40, "num_furniture", self.num_furniture, "0..40")
        _check(self.capture_radius_m > 0.3, "capture_radius_m", self.capture_radius_m, "> 0.3 m")
        _check(
            self.texel_m is None or 0.0002 <= self.texel_m <= 0.05,
            "texel_m",
            self.texel_m,
            "None or 0.0002..0.05 m",
        )
        _check(
            self.gt_voxel_foreground_m > 0,
            "gt_voxel_foreground_m",
            self.gt_voxel_foreground_m,
            "> 0",
        )
        _check(
            self.gt_voxel_background_m > 0,
            "gt_voxel_background_m",
            self.gt_voxel_background_m,
            "> 0",
        )
        half = min(self.room_size_m[:2]) / 2
        _check(
            self.rig.radius_m < half - 0.15,
            "rig.radius_m",
            self.rig.radius_m,
            f"cameras must stand inside the room (< {half - 0.15:.2f} m from the centre)",
        )
        _check(
            self.rig.camera_height_m < self.room_size_m[2] - 0.15,
            "rig.camera_height_m",
            self.rig.camera_height_m,
            "cameras must be below the ceiling",
        )
        for i, script in enumerate(self.actor_scripts):
            _check(
                isinstance(script, ActorScript),
                f"actor_scripts[{i}]",
                script,
                "an ActorScript",
            )
            xy = np.abs(np.asarray([k[1:] for k in script.keys], float))
            _check(
                bool(np.all(xy < np.asarray(self.room_size_m[:2]) / 2 - 0.3)),
                f"actor_scripts[{i}].keys",
                script.keys,
                "keys must lie inside the room, >= 0.3 m from the walls",
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SceneConfig:
        d = dict(d)
        rig_d: dict[str, Any] = {
            k: (tuple(v) if isinstance(v, list) else v) for k, v in d.pop("rig").items()
        }
        rig = RigSpec(**rig_d)
        real_d = dict(d.pop("realism"))
        if "light_keys" in real_d:
            real_d["light_keys"] = tuple(tuple(k) for k in real_d["light_keys"])
        realism = RealismConfig(**real_d)
        if "room_size_m" in d:
            d["room_size_m"] = tuple(d["room_size_m"])
        if "actor_scripts" in d:
            d["actor_scripts"] = tuple(ActorScript.from_dict(a) for a in d["actor_scripts"])
        return cls(rig=rig, realism=realism, **d)


# ----------------------------------------------------------------------------------- presets
def _ring() -> SceneConfig:
    return SceneConfig(
        name="synthetic-ring",
        rig=RigSpec(layout="ring", num_cameras=8, width=1280, height=720, focal_px=1000.0),
        num_frames=60,
        num_actors=3,
    )


def _arc7() -> SceneConfig:
    return SceneConfig(
        name="synthetic-arc7",
        rig=RigSpec(
            layout="arc",
            num_cameras=7,
            width=1920,
            height=1080,
            focal_px=1720.0,
            radius_m=3.6,
            camera_height_m=1.9,
            spacing_deg=15.0,
            distortion=STUDIO_DISTORTION,
            principal_offset_px=(-21.7, 10.7),
            jitter_m=0.06,
        ),
        num_frames=60,
        num_actors=2,
    )


def _demo() -> SceneConfig:
    return SceneConfig(
        name="synthetic-demo",
        rig=RigSpec(layout="ring", num_cameras=5, width=640, height=480, focal_px=540.0),
        num_frames=40,
        num_actors=2,
    )


def _object() -> SceneConfig:
    """Small-object capture (a turntable-like ring, as real object scans use): 0.1 % of the
    camera distance is ~0.6 mm, ~1.7 pixels at full resolution."""
    return SceneConfig(
        name="synthetic-object",
        rig=RigSpec(
            layout="ring",
            num_cameras=12,
            width=800,
            height=600,
            focal_px=1700.0,
            radius_m=0.55,
            camera_height_m=1.05,
            target=(0.0, 0.0, 0.80),
            jitter_m=0.005,
        ),
        num_frames=3,
        num_actors=0,
        background_frames=0,
        room_size_m=(3.0, 3.0, 2.5),
        num_furniture=0,
        texel_m=0.00025,
        gt_voxel_foreground_m=0.0005,
        gt_voxel_background_m=0.0005,
        centerpiece=True,
    )


PRESETS = {"ring": _ring, "arc7": _arc7, "demo": _demo, "object": _object}
"""Named scene presets."""


def preset_config(name: str, **overrides: Any) -> SceneConfig:
    """The preset ``name`` with ``overrides``: any field of ``SceneConfig``, ``RigSpec`` or
    ``RealismConfig`` by its name (e.g. ``num_cameras=5, width=320, noise_sigma=0``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    config = PRESETS[name]()
    rig_names = {f.name for f in fields(RigSpec)}
    real_names = {f.name for f in fields(RealismConfig)}
    scene_names = {f.name for f in fields(SceneConfig)}
    rig_kw = {k: v for k, v in overrides.items() if k in rig_names}
    real_kw = {k: v for k, v in overrides.items() if k in real_names}
    scene_kw = {k: v for k, v in overrides.items() if k in scene_names}
    unknown = set(overrides) - rig_names - real_names - scene_names
    if unknown:
        raise ValueError(f"unknown scene option(s) {sorted(unknown)}")
    if {"width", "height"} & set(rig_kw) and "focal_px" not in rig_kw:
        # Keep the field of view when only the resolution changes.
        w = rig_kw.get("width", config.rig.width)
        rig_kw["focal_px"] = config.rig.focal_px * w / config.rig.width
    if "principal_offset_px" not in rig_kw and "width" in rig_kw:
        s = rig_kw["width"] / config.rig.width
        off = config.rig.principal_offset_px
        rig_kw["principal_offset_px"] = (off[0] * s, off[1] * s)
    return dataclasses.replace(
        config,
        rig=dataclasses.replace(config.rig, **rig_kw),
        realism=dataclasses.replace(config.realism, **real_kw),
        **scene_kw,
    )


# ------------------------------------------------------------- people in a room (hd4, hd4p)
#: A phone or webcam lens after the vendor's own correction: mild barrel distortion.
PHONE_DISTORTION = (-0.06, 0.02, 0.0, 0.0, 0.0)


def _phone_realism() -> RealismConfig:
    """Phones' and webcams' noise, exposure and white balance per camera, mild blur, and
    ``ROOM_LIGHTS``' dimming stretch (hd4, site)."""
    return RealismConfig(
        noise_sigma=2.5,
        exposure_spread=0.08,
        white_balance_spread=0.04,
        blur_sigma_px=0.8,
        light_keys=ROOM_LIGHTS,
    )


def _hd4(portrait: bool = False) -> SceneConfig:
    """Four full-HD cameras 90 degrees apart in a room, no background clip, scripted actors."""
    w, h = (1080, 1920) if portrait else (1920, 1080)
    return SceneConfig(
        name="synthetic-hd4p" if portrait else "synthetic-hd4",
        rig=RigSpec(
            layout="ring",
            num_cameras=4,
            width=w,
            height=h,
            focal_px=1400.0,
            radius_m=3.3,
            camera_height_m=1.9,
            target=(0.0, 0.0, 1.0),
            azimuth_deg=45.0,
            distortion=PHONE_DISTORTION,
            principal_offset_px=(-5.2, 7.4) if portrait else (7.4, -5.2),
            jitter_m=0.08,
        ),
        num_frames=250,
        num_actors=3,
        fps=25.0,
        background_frames=0,
        room_size_m=(7.6, 7.2, 2.8),
        num_furniture=6,
        capture_radius_m=1.3,
        realism=_phone_realism(),
        actor_scripts=ROOM_SCRIPTS,
    )


PRESETS["hd4"] = _hd4
PRESETS["hd4p"] = functools.partial(_hd4, portrait=True)


def _site() -> SceneConfig:
    """Five full-HD cameras on poles around a yard, people walking, no background clip."""
    return SceneConfig(
        name="synthetic-site",
        rig=RigSpec(
            layout="ring",
            num_cameras=5,
            width=1920,
            height=1080,
            focal_px=1500.0,
            radius_m=14.0,
            camera_height_m=4.5,
            target=(0.0, 0.0, 0.9),
            azimuth_deg=20.0,
            distortion=PHONE_DISTORTION,
            jitter_m=0.3,
        ),
        num_frames=60,
        num_actors=4,
        fps=25.0,
        background_frames=0,
        room_size_m=(44.0, 44.0, 14.0),
        num_furniture=14,
        capture_radius_m=5.0,
        realism=_phone_realism(),  # the dimming stretch: a cloud passing over
        gt_voxel_foreground_m=0.01,
        gt_voxel_background_m=0.03,
    )


PRESETS["site"] = _site


# ----------------------------------------------------------------------------------- the rig
def make_rig(spec: RigSpec, seed: int = 0) -> Rig:
    """Cameras named cam0..cam{N-1}, placed by ``spec`` (metres, z up)."""
    rng = np.random.default_rng([seed, 101])
    n = spec.num_cameras
    target = np.asarray(spec.target, float)
    if spec.layout == "ring":
        offset = rng.uniform(-0.5, 0.5) * 2 * np.pi / n
        if spec.azimuth_deg is not None:
            offset = np.radians(spec.azimuth_deg)
        angles = 2 * np.pi * np.arange(n) / n + offset
    else:
        # Centred on the -y side, so that +x is to the right of the middle camera's image.
        angles = -np.pi / 2 + np.radians(spec.spacing_deg) * (np.arange(n) - (n - 1) / 2)
    cameras = []
    w, h = spec.width, spec.height
    for i, a in enumerate(angles):
        jitter = rng.normal(0.0, spec.jitter_m, 3) if spec.jitter_m > 0 else np.zeros(3)
        center = target + np.array([spec.radius_m * np.cos(a), spec.radius_m * np.sin(a), 0.0])
        center[2] = spec.camera_height_m + jitter[2] * 2
        center[:2] += jitter[:2] * 0.5
        aim = target + (rng.normal(0.0, spec.jitter_m, 3) if spec.jitter_m > 0 else 0.0)
        R, t = look_at(center.tolist(), np.asarray(aim, float).tolist())
        cx = (w - 1) / 2 + spec.principal_offset_px[0]
        cy = (h - 1) / 2 + spec.principal_offset_px[1]
        K = np.array([[spec.focal_px, 0.0, cx], [0.0, spec.focal_px, cy], [0.0, 0.0, 1.0]])
        cameras.append(
            Camera(name=f"cam{i}", width=w, height=h, K=K, R=R, t=t, dist=np.array(spec.distortion))
        )
    return Rig(cameras=tuple(cameras), unit="m")


# ----------------------------------------------------------------------------------- scene
@dataclass(frozen=True, kw_only=True)
class Lighting:
    """View-independent (Lambertian) lighting: ambient + a directional key + a ceiling lamp."""

    ambient: float = 0.4
    """Irradiance reaching every surface whatever its orientation."""
    key_direction: tuple[float, float, float] = (0.35, -0.25, 0.9)
    """Direction towards the key light (normalised on use)."""
    key: float = 0.38
    """Irradiance of the key light on a surface facing it."""
    lamp_position: tuple[float, float, float] = (0.3, 0.2, 2.9)
    """Position of the ceiling lamp, metres."""
    lamp: float = 0.9
    """Lamp intensity: irradiance ``lamp * cos / (distance^2 + lamp_softness_m^2)``."""
    lamp_softness_m: float = 1.0
    """Softens the lamp's fall-off near it (an extended light, no hot spot on heads)."""


@dataclass(frozen=True, kw_only=True, eq=False)
class SynthScene:
    """A built scene: geometry, textures, actors, rig and per-camera imaging parameters."""

    config: SceneConfig
    rig: Rig
    room: Room
    furniture: tuple[Box | Cylinder | Ellipsoid, ...]
    textures: tuple[Texture, ...]
    texture_kinds: tuple[str, ...]
    actors: tuple[motion.Actor, ...]
    lighting: Lighting
    camera_gains: NDArray[np.float32]
    """(N, 3) per-camera BGR gains (exposure x white balance)."""

    @property
    def num_frames(self) -> int:
        return self.config.num_frames

    def illumination(self, t: int | float) -> float:
        """Global light level at frame ``t`` (background frames are t < 0): the linear drift
        of ``illumination_change`` times the dimmer (``light_keys``)."""
        c = self.config
        a = c.realism.illumination_change
        level = 1.0
        if a != 0:
            start, end = -c.background_frames, c.num_frames - 1
            frac = (t - start) / max(end - start, 1)
            level = float(1.0 - a * np.clip(frac, 0.0, 1.0))
        return level * self.dimmer(t)

    def dimmer(self, t: int | float) -> float:
        """The dimmer's light level at frame ``t`` (1 without ``light_keys``)."""
        keys = self.config.realism.light_keys
        if not keys:
            return 1.0
        frames, levels = zip(*keys, strict=True)
        return float(np.interp(t, frames, levels))

    def stretches(self) -> dict[str, list[dict[str, Any]]]:
        """The sequence's difficult stretches as integer frame intervals [start, stop) inside
        0..num_frames (what gt/scene.json records, so that benchmarks need no hard-coded frames):

        * ``still``: an actor stands exactly still (every body part identical frame to frame);
        * ``away``: an actor has left the room and is not back yet;
        * ``seated``: a seated actor is present (low motion: talking gestures at most);
        * ``dimming``: the dimmer is below full light (``min_level``: its lowest level there).
        """
        T = self.config.num_frames

        def span(a: float, b: int) -> tuple[int, int]:
            return max(0, math.ceil(a)), min(T, b)

        out: dict[str, list[dict[str, Any]]] = {
            "still": [],
            "away": [],
            "seated": [],
            "dimming": [],
        }
        for actor in self.actors:
            for a, b in actor.still:
                start, stop = span(a, math.floor(b) + 1)
                frames = [t for t in range(start, stop) if actor.present(t)]
                if frames:
                    out["still"].append(
                        {"actor": actor.actor_id, "start": frames[0], "stop": frames[-1] + 1}
                    )
            presence = actor.presence or ((actor.enter_frame, actor.leave_frame),)
            for (_, leave), (enter, _) in itertools.pairwise(presence):
                start, stop = span(leave, math.ceil(enter))
                if stop > start:
                    out["away"].append({"actor": actor.actor_id, "start": start, "stop": stop})
            if actor.seated:
                for a, b in presence:
                    start, stop = span(a, math.ceil(b))
                    if stop > start:
                        out["seated"].append(
                            {"actor": actor.actor_id, "start": start, "stop": stop}
                        )
        levels = np.array([self.dimmer(t) for t in range(T)])
        dim = np.concatenate([[False], levels < 1 - 1e-9, [False]])
        edges = np.flatnonzero(np.diff(dim.astype(np.int8)))
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            out["dimming"].append(
                {
                    "start": int(start),
                    "stop": int(stop),
                    "min_level": round(float(levels[start:stop].min()), 6),
                }
            )
        return out

    def actors_at(self, t: float) -> list[motion.Actor]:
        return [a for a in self.actors if a.present(t)]

    def describe(self) -> dict[str, Any]:
        """JSON-safe summary (what ground truth's scene.json records)."""
        return {
            "room_size_m": list(self.config.room_size_m),
            "textures": list(self.texture_kinds),
            "furniture": [
                {
                    "kind": "box",
                    "center": f.center.tolist(),
                    "half": f.half.tolist(),
                    "yaw": f.yaw,
                }
                if isinstance(f, Box)
                else {
                    "kind": "ellipsoid",
                    "center": f.center.tolist(),
                    "radii": f.radii.tolist(),
                    "rotation": f.rotation.tolist(),
                }
                if isinstance(f, Ellipsoid)
                else {
                    "kind": "cylinder",
                    "center_xy": list(f.center_xy),
                    "radius": f.radius,
                    "z": [f.z0, f.z1],
                }
                for f in self.furniture
            ],
            "actors": [
                {
                    "id": a.actor_id,
                    "height_m": a.height_m,
                    "enter_frame": a.enter_frame,
                    "leave_frame": a.leave_frame,
                    "presence": [list(p) for p in a.presence] or [[a.enter_frame, a.leave_frame]],
                    "still": [list(p) for p in a.still],
                    "posture": "sit" if a.seated else "stand",
                }
                for a in self.actors
            ],
            "camera_gains": self.camera_gains.tolist(),
            "illumination": [
                self.illumination(t)
                for t in range(-self.config.background_frames, self.config.num_frames)
            ],
        }


def auto_texel(rig: Rig, target: F64) -> float:
    """Texel size matching the finest pixel footprint at the rig's target, metres."""
    fp = min(float(np.linalg.norm(c.center - target)) / c.focal_px for c in rig)
    return float(np.clip(fp, 0.002, 0.02))


class _TextureBank:
    """Collects texture requests; generation is cached per (kind, seed, shape, texel)."""

    def __init__(self, seed: int, texel_m: float) -> None:
        self.seed = seed
        self.texel_m = texel_m
        self.textures: list[Texture] = []
        self.kinds: list[str] = []

    def add(self, kind: str, extent_m: tuple[float, float], texel_scale: float = 1.0) -> int:
        texel = self.texel_m * texel_scale
        texel = max(texel, max(extent_m) / MAX_TEXTURE_SIDE)
        w = _round_side(extent_m[0] / texel)
        h = _round_side(extent_m[1] / texel)
        index = len(self.textures)
        self.textures.append(_cached_texture(kind, self.seed, index, (h, w), round(texel, 7)))
        self.kinds.append(kind)
        return index


def _round_side(n: float) -> int:
    """Texture side: a multiple of 64 (so that 6 mip levels tile exactly), at least 64."""
    return int(min(MAX_TEXTURE_SIDE, max(64, 64 * math.ceil(n / 64))))


@lru_cache(maxsize=64)
def _cached_texture(
    kind: str, seed: int, index: int, shape: tuple[int, int], texel: float
) -> Texture:
    return make_texture(kind, (seed, 7, index), shape, texel)


def build_scene(config: SceneConfig) -> SynthScene:
    """Build the scene of ``config`` (deterministic in ``config``)."""
    rng = np.random.default_rng([config.seed, 1])
    rig = make_rig(config.rig, config.seed)
    sx, sy, sz = config.room_size_m
    target = np.asarray(config.rig.target, float)
    texel = config.texel_m if config.texel_m is not None else auto_texel(rig, target)
    bank = _TextureBank(config.seed, texel)

    floor_kind = str(rng.choice(["planks", "tiles", "stone"]))
    wall_kinds = ["posters", "bricks", "stone", "paint"]
    rng.shuffle(wall_kinds)
    floor = bank.add(floor_kind, (sx, sy))
    ceiling = bank.add("paint", (sx, sy), texel_scale=4.0)
    walls = []
    for i, kind in enumerate(wall_kinds):
        extent = (sy if i < 2 else sx, sz)
        walls.append(bank.add(kind, extent))
    room = Room(
        half_x=sx / 2,
        half_y=sy / 2,
        height=sz,
        materials=(floor, ceiling, walls[0], walls[1], walls[2], walls[3]),
    )
    furniture: list[Box | Cylinder | Ellipsoid] = []
    if config.centerpiece:
        furniture += _centerpiece(np.asarray(config.rig.target, float), bank)
    furniture += _place_furniture(rng, config, rig, bank)
    actors = _make_actors(rng, config, bank, target)
    furniture += _chairs(actors, bank)

    n = len(rig)
    real = config.realism
    exposure = 1.0 + rng.uniform(-1, 1, (n, 1)) * real.exposure_spread
    wb = 1.0 + rng.uniform(-1, 1, (n, 3)) * real.white_balance_spread
    gains = (exposure * wb * real.brightness).astype(np.float32)
    scene = SynthScene(
        config=config,
        rig=rig,
        room=room,
        furniture=tuple(furniture),
        textures=tuple(bank.textures),
        texture_kinds=tuple(bank.kinds),
        actors=tuple(actors),
        lighting=Lighting(),
        camera_gains=gains,
    )
    for cam in rig:
        if not room.contains(cam.center, margin=0.05):
            raise ValueError(f"camera {cam.name!r} at {cam.center.round(2)} is outside the room")
    return scene


def _place_furniture(
    rng: np.random.Generator, config: SceneConfig, rig: Rig, bank: _TextureBank
) -> list[Box | Cylinder]:
    """Boxes and cylinders around the capture area, never in front of a camera."""
    sx, sy, _ = config.room_size_m
    target = np.asarray(config.rig.target, float)[:2]
    centers = rig.centers
    placed: list[tuple[F64, float]] = []
    items: list[Box | Cylinder] = []
    side_kinds = ["stone", "planks", "tiles", "posters", "paint", "fabric"]
    keep_clear = scripted_paths(config)
    tries = 0
    while len(items) < config.num_furniture and tries < 400:
        tries += 1
        is_box = rng.random() < 0.65
        if is_box:
            half = np.array([rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.45), rng.uniform(0.2, 0.6)])
            footprint = float(np.hypot(half[0], half[1]))
        else:
            radius = float(rng.uniform(0.15, 0.4))
            tall = float(rng.uniform(0.4, 2.2))
            footprint = radius
        r = rng.uniform(config.capture_radius_m + 0.4 + footprint, 0.5 * min(sx, sy) - footprint)
        ang = rng.uniform(0, 2 * np.pi)
        xy = target + r * np.array([np.cos(ang), np.sin(ang)])
        if abs(xy[0]) > sx / 2 - footprint - 0.02 or abs(xy[1]) > sy / 2 - footprint - 0.02:
            continue
        if any(np.linalg.norm(xy - p) < footprint + q + 0.1 for p, q in placed):
            continue
        # Keep clear of the cameras and of their lines of sight to the capture area.
        blocked = False
        for c in centers:
            if np.linalg.norm(xy - c[:2]) < footprint + 0.6:
                blocked = True
                break
            seg = target - c[:2]
            tt = np.clip(np.dot(xy - c[:2], seg) / np.dot(seg, seg), 0, 1)
            if np.linalg.norm(xy - (c[:2] + tt * seg)) < footprint + 0.5:
                blocked = True
                break
        if not blocked and len(keep_clear):
            gaps = np.linalg.norm(keep_clear - xy, axis=1)
            blocked = bool(gaps.min() < footprint + 0.6)
        if blocked:
            continue
        side = bank.add(str(rng.choice(side_kinds)), (2.0, 2.0))
        top = bank.add(str(rng.choice(["planks", "stone", "paint"])), (1.0, 1.0))
        if is_box:
            items.append(
                Box(
                    center=np.array([xy[0], xy[1], half[2]]),
                    half=half,
                    yaw=float(rng.uniform(0, np.pi)),
                    side_material=side,
                    top_material=top,
                )
            )
        else:
            items.append(
                Cylinder(
                    center_xy=(float(xy[0]), float(xy[1])),
                    radius=radius,
                    z0=0.0,
                    z1=tall,
                    side_material=side,
                    top_material=top,
                )
            )
        placed.append((xy, footprint))
    if len(items) < config.num_furniture:
        logger.info(
            "placed %d of %d furniture items (no free space)", len(items), config.num_furniture
        )
    return items


def _centerpiece(target: F64, bank: _TextureBank) -> list[Box | Cylinder | Ellipsoid]:
    """A table whose top is 6 cm below ``target`` and, on it, a carved object: a round base
    with studs (3 mm), a body with low-contrast faces carrying ribs (3 mm proud) and plaques
    (4 mm proud), a column and an elliptic dome."""
    tx, ty, tz = (float(v) for v in target)
    top = tz - 0.06
    items: list[Box | Cylinder | Ellipsoid] = [
        Box(
            center=np.array([tx, ty, top / 2]),
            half=np.array([0.8, 0.8, top / 2]),
            yaw=0.0,
            side_material=bank.add("paint", (1.6, 1.6)),
            top_material=bank.add("planks", (1.6, 1.6)),
        )
    ]
    base_top = top + 0.012
    items.append(
        Cylinder(
            center_xy=(tx, ty),
            radius=0.07,
            z0=top,
            z1=base_top,
            side_material=bank.add("stone", (0.45, 0.02)),
            top_material=bank.add("tiles", (0.14, 0.14)),
        )
    )
    stud = bank.add("stone", (0.05, 0.05))
    for k in range(10):
        a = 2 * np.pi * k / 10 + 0.2
        items.append(
            Cylinder(
                center_xy=(tx + 0.062 * np.cos(a), ty + 0.062 * np.sin(a)),
                radius=0.004,
                z0=base_top - 0.001,
                z1=base_top + 0.003,
                side_material=stud,
                top_material=stud,
            )
        )
    yaw = 0.3
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0, 0, 1]])
    half = np.array([0.045, 0.032, 0.05])
    center = np.array([tx, ty, base_top + half[2]])
    # Low-contrast faces (skin: 4 % variation; paint: 1.5 %), as plaster or grey plastic.
    items.append(
        Box(
            center=center,
            half=half,
            yaw=yaw,
            side_material=bank.add("skin", (0.3, 0.3)),
            top_material=bank.add("paint", (0.1, 0.1)),
        )
    )
    rib = bank.add("stone", (0.1, 0.1))
    for sign in (-1.0, 1.0):
        for y in (-0.018, 0.0, 0.018):
            local = np.array([sign * (half[0] + 0.0015), y, 0.0])
            items.append(
                Box(
                    center=center + rot @ local,
                    half=np.array([0.0015, 0.003, 0.042]),
                    yaw=yaw,
                    side_material=rib,
                    top_material=rib,
                )
            )
        local = np.array([0.0, sign * (half[1] + 0.002), 0.005])
        items.append(
            Box(
                center=center + rot @ local,
                half=np.array([0.028, 0.002, 0.03]),
                yaw=yaw,
                side_material=bank.add("posters", (0.1, 0.1)),
                top_material=rib,
            )
        )
    col = rot @ np.array([0.0, 0.05, 0.0])
    items.append(
        Cylinder(
            center_xy=(tx + col[0] + 0.03, ty + col[1]),
            radius=0.011,
            z0=base_top,
            z1=base_top + 0.085,
            side_material=bank.add("bricks", (0.08, 0.1)),
            top_material=rib,
        )
    )
    radii = np.array([0.04, 0.028, 0.028])
    items.append(
        Ellipsoid(
            center=center + np.array([0.0, 0.0, half[2]]),
            rotation=rot,
            radii=radii,
            material=bank.add("fabric", (0.26, 0.1)),
            u_period_m=float(bank.textures[-1].period_m[0]),
        )
    )
    return items


def _make_actors(
    rng: np.random.Generator, config: SceneConfig, bank: _TextureBank, target: F64
) -> list[motion.Actor]:
    T = config.num_frames
    actors: list[motion.Actor] = []
    center = target[:2]
    half = min(config.room_size_m[:2]) / 2
    edge = min(config.capture_radius_m + 1.0, half - 0.5)
    scripts = config.actor_scripts
    for k in range(config.num_actors):
        aid = k + 1
        script = scripts[k] if k < len(scripts) else None
        if script is None:
            enter, leave, times, points = _random_motion(rng, config, k, actors, center, edge)
        else:
            times = np.array([key[0] for key in script.keys], float)
            points = np.array([key[1:] for key in script.keys], float)
            presence = script.presence(T)
            enter, leave = presence[0][0], presence[-1][1]
        look = motion.ActorLook(
            shirt=bank.add("fabric", (0.4, 0.8), texel_scale=0.75),
            trousers=bank.add(str(rng.choice(["fabric", "stone"])), (0.4, 0.8), texel_scale=0.75),
            skin=bank.add("skin", (0.3, 0.3), texel_scale=1.5),
            hair=bank.add("hair", (0.3, 0.3), texel_scale=0.75),
            shoes=bank.add("stone", (0.3, 0.3)),
            shirt_period_m=bank.textures[-5].period_m[0],
            trousers_period_m=bank.textures[-4].period_m[0],
            skin_period_m=bank.textures[-3].period_m[0],
            hair_period_m=bank.textures[-2].period_m[0],
            shoes_period_m=bank.textures[-1].period_m[0],
        )
        actor = motion.Actor(
            actor_id=aid,
            height_m=float(rng.uniform(1.6, 1.9)),
            width_scale=float(rng.uniform(0.9, 1.15)),
            enter_frame=enter,
            leave_frame=leave,
            key_times=times,
            key_positions=points,
            stride_m=float(rng.uniform(1.2, 1.5)),
            phase0=float(rng.uniform(0, 2 * np.pi)),
            look=look,
        )
        if script is not None:
            if script.facing_deg is not None:
                facing = math.radians(script.facing_deg)
            else:
                to_target = center - points[0]
                facing = math.atan2(to_target[1], to_target[0])
            actor = dataclasses.replace(
                actor,
                presence=script.presence(T),
                still=tuple((float(a), float(b)) for a, b in script.still),
                seated=script.posture == "sit",
                facing=facing,
                gesture=script.gesture,
                gesture_period=script.gesture_period_frames,
                turn_frames=script.turn_s * config.fps,
            )
        actors.append(actor)
    return actors


def _random_motion(
    rng: np.random.Generator,
    config: SceneConfig,
    k: int,
    actors: list[motion.Actor],
    center: F64,
    edge: float,
) -> tuple[float, float, F64, F64]:
    """Presence and keyframes of random actor ``k``: actor 1 is there throughout; the others
    may enter late and/or leave early; actor 2 is steered to pass close to actor 1."""
    T = config.num_frames
    enters = k > 0 and T >= 10 and rng.random() < 0.7
    leaves = k > 0 and T >= 10 and not enters and rng.random() < 0.6
    enter = float(rng.uniform(0.1, 0.35) * T) if enters else 0.0
    leave = float(rng.uniform(0.6, 0.9) * T) if leaves else float(T)
    times, points = motion.random_path(
        rng,
        start_frame=enter,
        end_frame=leave,
        fps=config.fps,
        area_radius_m=config.capture_radius_m,
        edge_radius_m=edge,
        enters=enters,
        leaves=leaves,
        center=center,
    )
    if leaves:
        leave = float(times[-1])
    if k == 1 and actors:
        lo = max(enter, actors[0].enter_frame) + 0.2 * config.fps
        hi = min(leave, actors[0].leave_frame) - 0.2 * config.fps
        points = motion.steer_close(
            times, points, actors[0], distance_m=0.75, window=(lo, hi), sigma_frames=config.fps
        )
    return enter, leave, times, points


def _chairs(actors: Sequence[motion.Actor], bank: _TextureBank) -> list[Box]:
    """A chair (seat and backrest boxes, static) under every seated actor."""
    items: list[Box] = []
    for actor in actors:
        if not actor.seated:
            continue
        side = bank.add("planks", (1.0, 1.0))
        top = bank.add("fabric", (0.6, 0.6))
        heading = actor.heading(actor.enter_frame)
        for center, half in motion.chair_boxes(
            actor.position(actor.enter_frame), heading, actor.height_m, actor.width_scale
        ):
            items.append(
                Box(center=center, half=half, yaw=heading, side_material=side, top_material=top)
            )
    return items


def scripted_paths(config: SceneConfig, samples_per_frame: float = 0.5) -> F64:
    """(M, 2) floor points along the scripted actors' paths while they are present (to keep
    furniture off them)."""
    pts = [np.zeros((0, 2))]
    for script in config.actor_scripts[: config.num_actors]:
        times = np.array([key[0] for key in script.keys], float)
        points = np.array([key[1:] for key in script.keys], float)
        path = scripted_path(times, points, script.still)
        for a, b in script.presence(config.num_frames):
            lo, hi = max(a, path.x[0]), min(b, path.x[-1])
            n = max(2, int((hi - lo) * samples_per_frame) + 1)
            pts.append(path(np.linspace(lo, hi, n)) if hi > lo else points[:1])
    return np.concatenate(pts)
