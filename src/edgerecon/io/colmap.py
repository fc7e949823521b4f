"""COLMAP sparse models: read and write them (text and binary), turn them into a rig, and
build one from a rig and a point cloud.

The layout is COLMAP's documented one (``doc/format.rst``, ``scripts/python/read_write_model.py``):

* ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``;
  ``cameras.bin``: uint64 count, then per camera int32 id, int32 model id, uint64 width,
  uint64 height, float64 params.
* ``images.txt``: per image ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and a line of
  ``X Y POINT3D_ID`` triples (-1 = no 3D point); ``images.bin``: uint64 count, then per image
  uint32 id, float64 q[4], float64 t[3], uint32 camera id, the name NUL-terminated, uint64
  number of 2D points, per point float64 x, float64 y, int64 3D point id.
* ``points3D.txt``: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` with ``IMAGE_ID POINT2D_IDX``
  pairs; ``points3D.bin``: uint64 count, then per point uint64 id, float64 xyz, uint8 rgb,
  float64 error, uint64 track length, per track element int32 image id, int32 2D point index.

Poses are ``cam_from_world`` (``X_cam = R(q) X + t``, q = (w, x, y, z)). COLMAP puts the
centre of the top-left pixel at (0.5, 0.5), edgerecon at (0, 0): principal points shift by
0.5 pixel. The text writer records the rig's unit and up in a comment
(``# edgerecon: unit=mm up=0,0,-1``) that the reader understands and COLMAP ignores.

**A model as a rig** (``rig_from_colmap``): a static rig's images are grouped into cameras —
by COLMAP camera id, by the folder of the image name (``cam0/000123.png``) or, when neither
gives one pose per group, by pose. A camera's images must share one pose (within 1 % of the
rig's size and 1 degree; the mean pose is used) and one set of intrinsics. Cameras are named
after their folder, after their single image (``img0.jpg`` -> ``img0``) or ``cam<id>``;
``ColmapRig.frames`` lists each camera's images in natural order: the frames of a dataset.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig, rotation_angle_deg
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, calibrated_rig, lens_camera
from edgerecon.io._errors import in_file
from edgerecon.io.frames import IMAGE_EXTENSIONS, natural_key
from edgerecon.io.ply import atomic_write_bytes, atomic_write_text
from edgerecon.io.records import Item, walk_records
from edgerecon.types import CalibrationError, DataError

logger = logging.getLogger(__name__)

#: COLMAP camera models: name -> (model id, number of parameters).
CAMERA_MODELS: dict[str, tuple[int, int]] = {
    "SIMPLE_PINHOLE": (0, 3),
    "PINHOLE": (1, 4),
    "SIMPLE_RADIAL": (2, 4),
    "RADIAL": (3, 5),
    "OPENCV": (4, 8),
    "OPENCV_FISHEYE": (5, 8),
    "FULL_OPENCV": (6, 12),
    "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4),
    "RADIAL_FISHEYE": (9, 5),
    "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
}
_MODEL_BY_ID = {mid: name for name, (mid, _) in CAMERA_MODELS.items()}
#: The models edgerecon's camera (OpenCV k1 k2 p1 p2 k3) represents exactly.
RIG_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_META = re.compile(r"#\s*edgerecon:\s*(.*)")
_INVALID_ID = -1


# ============================================================================== data
@dataclass(frozen=True, kw_only=True, eq=False)
class ColmapCamera:
    """One COLMAP camera (intrinsics)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: NDArray[np.float64]
    """Model parameters in COLMAP's order and pixel convention."""
    origin: str = ""
    """Where it was read from (``file:line``), for messages."""


@dataclass(frozen=True, kw_only=True, eq=False)
class ColmapImage:
    """One registered image: pose, camera and 2D points."""

    image_id: int
    qvec: NDArray[np.float64]
    """(4,) unit quaternion (w, x, y, z) of ``cam_from_world``."""
    tvec: NDArray[np.float64]
    """(3,) translation of ``cam_from_world``."""
    camera_id: int
    name: str
    """Image file name relative to the image folder (may contain '/')."""
    points2D: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    """(M, 2) pixel coordinates (COLMAP convention: top-left pixel centre at (0.5, 0.5))."""
    point3D_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    """(M,) id of the 3D point of each 2D point, -1 for none."""
    origin: str = ""
    """Where it was read from (``file:line``), for messages."""

    @property
    def R(self) -> NDArray[np.float64]:
        return quaternion_to_rotation(self.qvec)

    @property
    def center(self) -> NDArray[np.float64]:
        return np.asarray(-self.R.T @ self.tvec, np.float64)


@dataclass(frozen=True, kw_only=True, eq=False)
class ColmapPoints:
    """The 3D points of a model, column-wise (a million points stay cheap)."""

    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    """(P,) point ids."""
    xyz: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    rgb: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    error: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    """(P,) mean reprojection error in pixels."""
    track_offsets: NDArray[np.int64] = field(default_factory=lambda: np.zeros(1, np.int64))
    """(P + 1,) point k's track is ``track_image_ids[track_offsets[k]:track_offsets[k+1]]``."""
    track_image_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    track_point2D_idxs: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def track_lengths(self) -> NDArray[np.int64]:
        return np.diff(self.track_offsets)


@dataclass(frozen=True, kw_only=True, eq=False)
class ColmapModel:
    """A COLMAP sparse model."""

    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points3D: ColmapPoints = field(default_factory=ColmapPoints)
    meta: dict[str, str] = field(default_factory=dict)
    """``unit`` / ``up`` recorded by edgerecon's writer (empty for other models)."""

    def check(self) -> None:
        """Raise ``DataError`` when ids refer to nothing (what COLMAP would reject)."""
        for img in self.images.values():
            if img.camera_id not in self.cameras:
                raise DataError(
                    f"image {img.name!r} uses camera {img.camera_id}, which the model lacks"
                )
            if len(img.points2D) != len(img.point3D_ids):
                raise DataError(f"image {img.name!r}: points2D and point3D_ids differ in length")
        pts = self.points3D
        if len(pts.track_image_ids):
            known = np.array(sorted(self.images), np.int64)
            bad = ~np.isin(pts.track_image_ids, known)
            if bad.any():
                raise DataError(
                    f"a track refers to image {int(pts.track_image_ids[bad][0])}, not in the model"
                )


# ============================================================================== reading
def find_colmap_model(path: str | os.PathLike[str]) -> Path | None:
    """The folder holding a model (``cameras`` + ``images`` in .txt or .bin) at ``path``,
    ``path/sparse`` or ``path/sparse/0``; None when there is none."""
    p = Path(path)
    if p.is_file():
        p = p.parent
    for sub in (p, p / "sparse", p / "sparse" / "0"):
        for ext in (".txt", ".bin"):
            if (sub / f"cameras{ext}").is_file() and (sub / f"images{ext}").is_file():
                return sub
    return None


def read_colmap_model(path: str | os.PathLike[str], *, points: bool = True) -> ColmapModel:
    """Read a COLMAP model folder (text or binary, detected; binary wins when both are
    there, as in COLMAP). ``points=False`` skips points3D and the text form's 2D points (a rig
    needs only the poses)."""
    folder = find_colmap_model(path)
    if folder is None:
        base = Path(path).parent if Path(path).is_file() else Path(path)
        for ext in (".txt", ".bin"):
            have = [n for n in ("cameras", "images") if (base / f"{n}{ext}").is_file()]
            if len(have) == 1:
                missing = "images" if have == ["cameras"] else "cameras"
                raise CalibrationError(
                    f"COLMAP model incomplete: {base / (missing + ext)} not found"
                )
        raise CalibrationError(
            f"{path}: no COLMAP model (cameras.txt + images.txt or cameras.bin + images.bin)"
        )
    binary = (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file()
    if binary:
        cameras = _read_cameras_bin(folder / "cameras.bin")
        images = _read_images_bin(folder / "images.bin")
        meta: dict[str, str] = {}
        pts_file = folder / "points3D.bin"
        pts = _read_points_bin(pts_file) if points and pts_file.is_file() else ColmapPoints()
    else:
        cameras, meta = _read_cameras_txt(folder / "cameras.txt")
        images = _read_images_txt(folder / "images.txt", points2D=points)
        pts_file = folder / "points3D.txt"
        pts = _read_points_txt(pts_file) if points and pts_file.is_file() else ColmapPoints()
    return ColmapModel(cameras=cameras, images=images, points3D=pts, meta=meta)


def _camera(
    cam_id: int, model: str, width: int, height: int, params: NDArray[np.float64], where: str
) -> ColmapCamera:
    if model not in CAMERA_MODELS:
        raise CalibrationError(
            f"{where}: unknown COLMAP camera model {model!r} (known: {', '.join(CAMERA_MODELS)})"
        )
    n = CAMERA_MODELS[model][1]
    if params.size != n:
        raise CalibrationError(f"{where}: {model} takes {n} parameters, got {params.size}")
    return ColmapCamera(
        camera_id=cam_id, model=model, width=width, height=height, params=params, origin=where
    )


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"COLMAP model incomplete: {path} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read ({exc})") from None


def _read_cameras_txt(path: Path) -> tuple[dict[int, ColmapCamera], dict[str, str]]:
    meta: dict[str, str] = {}
    cameras: dict[int, ColmapCamera] = {}
    for lineno, line in enumerate(_read_text(path).splitlines(), start=1):
        m = _META.match(line.strip())
        if m:
            for word in m.group(1).split():
                if "=" in word:
                    k, v = word.split("=", 1)
                    meta[k] = v
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        words = line.split()
        where = f"{path}:{lineno}"
        try:
            cam_id, model = int(words[0]), words[1]
            width, height = int(words[2]), int(words[3])
            params = np.array([float(v) for v in words[4:]])
        except (IndexError, ValueError) as exc:
            raise CalibrationError(f"{where}: malformed camera line ({exc})") from None
        cameras[cam_id] = _camera(cam_id, model, width, height, params, where)
    return cameras, meta


def _read_images_txt(path: Path, points2D: bool = True) -> dict[int, ColmapImage]:
    """Each image has a pose line, normally followed by its (possibly empty) 2D points line.
    Hand-written files often leave the points lines out, so a line counts as a points line
    only if it directly follows a pose line and looks like one. ``points2D=False`` skips
    their contents (a rig needs only the poses; SfM models have thousands per image)."""
    images: dict[int, ColmapImage] = {}
    last: ColmapImage | None = None
    for lineno, line in enumerate(_read_text(path).splitlines(), start=1):
        if line.lstrip().startswith("#"):
            continue
        words = line.split()
        if last is not None:
            prev, last = last, None
            if not words:
                continue
            if len(words) % 3 == 0:
                try:
                    values = np.array(words, dtype=np.float64)
                except ValueError:
                    values = None
                if values is not None:
                    if points2D:
                        triples = values.reshape(-1, 3)
                        images[prev.image_id] = dataclasses.replace(
                            prev,
                            points2D=triples[:, :2].copy(),
                            point3D_ids=triples[:, 2].astype(np.int64),
                        )
                    continue
        if not words:
            continue
        where = f"{path}:{lineno}"
        if len(words) < 10:
            raise CalibrationError(
                f"{where}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', "
                f"got {len(words)} fields"
            )
        try:
            image_id = int(words[0])
            q = np.array([float(v) for v in words[1:5]])
            t = np.array([float(v) for v in words[5:8]])
            cam_id = int(words[8])
        except ValueError as exc:
            raise CalibrationError(f"{where}: {exc}") from None
        name = " ".join(words[9:])
        if image_id in images:
            raise CalibrationError(f"{where}: image id {image_id} appears twice")
        img = ColmapImage(
            image_id=image_id, qvec=q, tvec=t, camera_id=cam_id, name=name, origin=where
        )
        images[image_id] = img
        last = img
    return images


def _read_points_txt(path: Path) -> ColmapPoints:
    ids, xyz, rgb, err, lengths, tracks = [], [], [], [], [], []
    for lineno, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        words = line.split()
        try:
            ids.append(int(words[0]))
            xyz.append([float(v) for v in words[1:4]])
            rgb.append([int(v) for v in words[4:7]])
            err.append(float(words[7]))
            track = [int(v) for v in words[8:]]
        except (IndexError, ValueError) as exc:
            raise DataError(f"{path}:{lineno}: malformed 3D point line ({exc})") from None
        if len(track) % 2:
            raise DataError(f"{path}:{lineno}: a track is (IMAGE_ID, POINT2D_IDX) pairs")
        lengths.append(len(track) // 2)
        tracks.extend(track)
    offsets = np.zeros(len(ids) + 1, np.int64)
    np.cumsum(lengths, out=offsets[1:])
    pairs = np.array(tracks, np.int64).reshape(-1, 2)
    return ColmapPoints(
        ids=np.array(ids, np.int64),
        xyz=np.array(xyz, np.float64).reshape(-1, 3),
        rgb=np.array(rgb, np.uint8).reshape(-1, 3),
        error=np.array(err, np.float64),
        track_offsets=offsets,
        track_image_ids=pairs[:, 0].copy(),
        track_point2D_idxs=pairs[:, 1].copy(),
    )


def _read_bytes(path: Path) -> NDArray[np.uint8]:
    try:
        return np.fromfile(path, np.uint8)
    except FileNotFoundError:
        raise CalibrationError(f"COLMAP model incomplete: {path} not found") from None


def _u64(buf: NDArray[np.uint8], pos: int, path: Path) -> int:
    if pos + 8 > len(buf):
        raise CalibrationError(f"{path}: truncated")
    return int(buf[pos : pos + 8].view("<u8")[0])


def _read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    buf = _read_bytes(path)
    n = _u64(buf, 0, path)
    pos = 8
    cameras = {}
    for k in range(n):
        if pos + 24 > len(buf):
            raise CalibrationError(f"{path}: truncated in camera #{k}")
        cam_id, model_id = (int(v) for v in buf[pos : pos + 8].view("<i4"))
        width, height = (int(v) for v in buf[pos + 8 : pos + 24].view("<u8"))
        pos += 24
        model = _MODEL_BY_ID.get(model_id)
        if model is None:
            raise CalibrationError(f"{path}: camera {cam_id} has unknown model id {model_id}")
        num = CAMERA_MODELS[model][1]
        if pos + 8 * num > len(buf):
            raise CalibrationError(f"{path}: truncated in camera {cam_id}")
        params = buf[pos : pos + 8 * num].view("<f8").astype(np.float64)
        pos += 8 * num
        cameras[cam_id] = _camera(cam_id, model, width, height, params, f"{path} camera {cam_id}")
    return cameras


def _read_images_bin(path: Path) -> dict[int, ColmapImage]:
    buf = _read_bytes(path)
    raw = buf.tobytes()
    n = _u64(buf, 0, path)
    pos = 8
    images = {}
    for k in range(n):
        if pos + 64 > len(buf):
            raise CalibrationError(f"{path}: truncated in image #{k}")
        image_id = int(buf[pos : pos + 4].view("<u4")[0])
        qt = buf[pos + 4 : pos + 60].view("<f8").astype(np.float64)
        cam_id = int(buf[pos + 60 : pos + 64].view("<u4")[0])
        pos += 64
        end = raw.find(b"\0", pos)
        if end < 0:
            raise CalibrationError(f"{path}: truncated name of image {image_id}")
        name = raw[pos:end].decode("utf-8")
        pos = end + 1
        m = _u64(buf, pos, path)
        pos += 8
        if pos + 24 * m > len(buf):
            raise CalibrationError(f"{path}: truncated points of image {image_id}")
        rec = buf[pos : pos + 24 * m].view(np.dtype([("xy", "<f8", 2), ("id", "<i8")]))
        pos += 24 * m
        images[image_id] = ColmapImage(
            image_id=image_id,
            qvec=qt[:4].copy(),
            tvec=qt[4:].copy(),
            camera_id=cam_id,
            name=name,
            points2D=rec["xy"].astype(np.float64),
            point3D_ids=rec["id"].astype(np.int64),
        )
    return images


def _read_points_bin(path: Path) -> ColmapPoints:
    buf = _read_bytes(path)
    n = _u64(buf, 0, path)
    # id u64 | xyz 3 f8 | rgb 3 u1 | error f8 | track: u64 count, (i4 image, i4 idx) each
    recs = walk_records(
        buf, 8, n, (Item(8), Item(24), Item(3), Item(8), Item(8, count_size=8)), what=str(path)
    )
    xyz = np.stack([recs.field(1, "<f8", at=8 * i) for i in range(3)], axis=1)
    rgb = np.stack([recs.field(2, "u1", at=i) for i in range(3)], axis=1)
    entries, offsets = recs.list_entries(4, "<i8")
    pairs = np.asarray(entries).view("<i4").reshape(-1, 2)
    return ColmapPoints(
        ids=recs.field(0, "<u8").astype(np.int64),
        xyz=xyz.astype(np.float64),
        rgb=rgb.astype(np.uint8),
        error=recs.field(3, "<f8").astype(np.float64),
        track_offsets=offsets,
        track_image_ids=pairs[:, 0].astype(np.int64),
        track_point2D_idxs=pairs[:, 1].astype(np.int64),
    )


# ============================================================================== writing
def write_colmap_model(
    path: str | os.PathLike[str], model: ColmapModel, *, binary: bool = False
) -> Path:
    """Write ``model`` into the folder ``path`` (``cameras``, ``images``, ``points3D`` in
    ``.txt`` or ``.bin``), each file atomically. Returns the folder."""
    model.check()
    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        atomic_write_bytes(folder / "cameras.bin", lambda f: f.write(_cameras_bin(model)))
        atomic_write_bytes(folder / "images.bin", lambda f: f.write(_images_bin(model)))
        atomic_write_bytes(folder / "points3D.bin", lambda f: f.write(_points_bin(model)))
    else:
        atomic_write_text(folder / "cameras.txt", _cameras_txt(model))
        atomic_write_text(folder / "images.txt", _images_txt(model))
        atomic_write_text(folder / "points3D.txt", _points_txt(model))
    return folder


def _num(v: float) -> str:
    return repr(float(v))


def _cameras_txt(model: ColmapModel) -> str:
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(model.cameras)}",
    ]
    if model.meta:
        lines.append("# edgerecon: " + " ".join(f"{k}={v}" for k, v in model.meta.items()))
    for cam in sorted(model.cameras.values(), key=lambda c: c.camera_id):
        lines.append(
            f"{cam.camera_id} {cam.model} {cam.width} {cam.height} "
            + " ".join(_num(p) for p in cam.params)
        )
    return "\n".join(lines) + "\n"


def _images_txt(model: ColmapModel) -> str:
    n_obs = sum(int(np.count_nonzero(i.point3D_ids >= 0)) for i in model.images.values())
    mean = n_obs / len(model.images) if model.images else 0
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(model.images)}, mean observations per image: {mean:g}",
    ]
    for img in sorted(model.images.values(), key=lambda i: i.image_id):
        if any(ch.isspace() for ch in img.name):
            raise DataError(f"image {img.name!r}: COLMAP image names cannot contain whitespace")
        lines.append(
            f"{img.image_id} "
            + " ".join(_num(v) for v in (*img.qvec, *img.tvec))
            + f" {img.camera_id} {img.name}"
        )
        lines.append(
            " ".join(
                f"{_num(x)} {_num(y)} {int(pid)}"
                for (x, y), pid in zip(img.points2D, img.point3D_ids, strict=True)
            )
        )
    return "\n".join(lines) + "\n"


def _points_txt(model: ColmapModel) -> str:
    pts = model.points3D
    lengths = pts.track_lengths
    mean = float(lengths.mean()) if len(lengths) else 0.0
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(pts)}, mean track length: {mean:g}",
    ]
    pairs = np.stack([pts.track_image_ids, pts.track_point2D_idxs], axis=1)
    for k in range(len(pts)):
        a, b = int(pts.track_offsets[k]), int(pts.track_offsets[k + 1])
        x, y, z = pts.xyz[k]
        r, g, bl = (int(v) for v in pts.rgb[k])
        track = " ".join(f"{int(i)} {int(j)}" for i, j in pairs[a:b])
        lines.append(
            f"{int(pts.ids[k])} {_num(x)} {_num(y)} {_num(z)} {r} {g} {bl} "
            f"{_num(pts.error[k])} {track}"
        )
    return "\n".join(lines) + "\n"


def _cameras_bin(model: ColmapModel) -> bytes:
    out = [np.array([len(model.cameras)], "<u8").tobytes()]
    for cam in sorted(model.cameras.values(), key=lambda c: c.camera_id):
        out.append(np.array([cam.camera_id, CAMERA_MODELS[cam.model][0]], "<i4").tobytes())
        out.append(np.array([cam.width, cam.height], "<u8").tobytes())
        out.append(np.asarray(cam.params, "<f8").tobytes())
    return b"".join(out)


def _images_bin(model: ColmapModel) -> bytes:
    out = [np.array([len(model.images)], "<u8").tobytes()]
    for img in sorted(model.images.values(), key=lambda i: i.image_id):
        out.append(np.array([img.image_id], "<u4").tobytes())
        out.append(np.asarray([*img.qvec, *img.tvec], "<f8").tobytes())
        out.append(np.array([img.camera_id], "<u4").tobytes())
        out.append(img.name.encode("utf-8") + b"\0")
        out.append(np.array([len(img.points2D)], "<u8").tobytes())
        rec = np.zeros(len(img.points2D), np.dtype([("xy", "<f8", 2), ("id", "<i8")]))
        rec["xy"] = img.points2D
        rec["id"] = img.point3D_ids
        out.append(rec.tobytes())
    return b"".join(out)


def _points_bin(model: ColmapModel) -> bytes:
    pts = model.points3D
    n = len(pts)
    head_t = np.dtype(
        [("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"), ("len", "<u8")]
    )
    head = np.zeros(n, head_t)
    head["id"], head["xyz"], head["rgb"] = pts.ids, pts.xyz, pts.rgb
    head["err"], head["len"] = pts.error, pts.track_lengths
    lengths = pts.track_lengths
    sizes = head_t.itemsize + 8 * lengths
    starts = np.zeros(n + 1, np.int64)
    np.cumsum(sizes, out=starts[1:])
    body = np.zeros(int(starts[-1]), np.uint8)
    if n:
        hb = head.view(np.uint8).reshape(n, head_t.itemsize)
        body[starts[:-1, None] + np.arange(head_t.itemsize)] = hb
        pairs = np.stack([pts.track_image_ids, pts.track_point2D_idxs], axis=1).astype("<i4")
        if len(pairs):
            rows = np.repeat(np.arange(n), lengths)
            within = np.arange(len(pairs)) - pts.track_offsets[rows]
            at = starts[rows] + head_t.itemsize + 8 * within
            body[at[:, None] + np.arange(8)] = pairs.view(np.uint8).reshape(-1, 8)
    return np.array([n], "<u8").tobytes() + body.tobytes()


# ============================================================================== rig <-> model
def colmap_intrinsics(cam: ColmapCamera) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(K, dist) of a COLMAP camera in edgerecon's pixel convention (OpenCV k1 k2 p1 p2 k3)."""
    model, params = cam.model, cam.params
    if model not in RIG_MODELS:
        raise CalibrationError(
            f"unsupported COLMAP camera model {model!r} (supported: {', '.join(RIG_MODELS)})"
        )
    dist = np.zeros(5)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = params[0]
        cx, cy = params[1], params[2]
        if model == "SIMPLE_RADIAL":
            dist[0] = params[3]
        elif model == "RADIAL":
            dist[:2] = params[3:5]
    else:
        fx, fy, cx, cy = params[:4]
        if model in ("OPENCV", "FULL_OPENCV"):
            dist[:4] = params[4:8]
        if model == "FULL_OPENCV":
            if np.any(params[9:12] != 0):
                raise CalibrationError(
                    "FULL_OPENCV with non-zero rational coefficients k4..k6 is not supported"
                )
            dist[4] = params[8]
    # COLMAP: centre of the top-left pixel at (0.5, 0.5); edgerecon: at (0, 0).
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, dist


def colmap_fisheye(cam: ColmapCamera) -> FisheyeLens | None:
    """The lens of an ``OPENCV_FISHEYE`` camera (fx fy cx cy k1 k2 k3 k4: OpenCV's fisheye
    model) in edgerecon's pixel convention; None for the other models."""
    if cam.model != "OPENCV_FISHEYE":
        return None
    fx, fy, cx, cy, *D = cam.params[:8]
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return FisheyeLens(width=cam.width, height=cam.height, K=K, D=np.asarray(D))


def camera_to_colmap(cam: Camera, camera_id: int) -> ColmapCamera:
    """The simplest COLMAP model that holds ``cam`` exactly (PINHOLE, OPENCV, FULL_OPENCV)."""
    if cam.K[0, 1] != 0:
        raise CalibrationError(f"camera {cam.name!r}: COLMAP cannot represent a skewed K")
    fx, fy = cam.K[0, 0], cam.K[1, 1]
    cx, cy = cam.K[0, 2] + 0.5, cam.K[1, 2] + 0.5
    k1, k2, p1, p2, k3 = cam.dist
    if not cam.has_distortion:
        model, params = "PINHOLE", [fx, fy, cx, cy]
    elif k3 == 0:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    else:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    return ColmapCamera(
        camera_id=camera_id,
        model=model,
        width=cam.width,
        height=cam.height,
        params=np.array(params, np.float64),
    )


def rig_meta(rig: Rig) -> dict[str, str]:
    return {"unit": rig.unit, "up": ",".join(repr(float(v)) for v in rig.up)}


@dataclass(frozen=True, kw_only=True, eq=False)
class ColmapRig:
    """A COLMAP model read as a static rig."""

    rig: Rig
    frames: dict[str, list[str]]
    """Per rig camera, its images' names in natural order (the frames of a dataset)."""
    grouping: str
    """How images became cameras: "image" (one each), "camera_id", "folder" or "pose"."""
    pose_spread: dict[str, tuple[float, float]]
    """Per camera: largest distance of an image's centre from the mean (rig units) and
    largest rotation from the mean (degrees)."""
    lenses: dict[str, FisheyeLens] = field(default_factory=dict)
    """The ``OPENCV_FISHEYE`` cameras' lenses: those cameras are in ``rig`` as the pinhole
    cameras their frames are rectified to (``geometry.lens``)."""


def rig_from_colmap(
    model: ColmapModel,
    *,
    unit: str | None = None,
    up: Sequence[float] | None = None,
    source: str = "COLMAP model",
    max_spread: float = 0.01,
    max_spread_deg: float = 1.0,
) -> ColmapRig:
    """Group the model's images into the cameras of a static rig (see the module docstring).

    ``max_spread`` (share of the median distance between cameras) and ``max_spread_deg``
    bound how far the poses of one camera's images may differ.
    """
    images = sorted(model.images.values(), key=lambda i: natural_key(i.name))
    if not images:
        raise CalibrationError(f"{source}: the model has no images")
    for img in images:
        if img.camera_id not in model.cameras:
            raise CalibrationError(
                f"{img.origin or source}: camera {_strip_ext(img.name)!r} uses CAMERA_ID {img.camera_id}, "
                "not in the model's cameras"
            )
        norm = float(np.linalg.norm(img.qvec))
        if not abs(norm - 1.0) < 1e-3:
            raise CalibrationError(
                f"{img.origin or source}: camera {_strip_ext(img.name)!r}: quaternion norm is {norm:.6g}, "
                "expected 1"
            )
    centers = np.array([img.center for img in images])
    rotations = [quaternion_to_rotation(img.qvec / np.linalg.norm(img.qvec)) for img in images]
    by_pose = _pose_groups(centers, rotations, max_spread, max_spread_deg)
    if len(by_pose) < 3:
        raise CalibrationError(
            f"{source}: a rig needs at least 3 cameras; its {len(images)} image(s) show "
            f"{len(by_pose)} distinct pose(s)"
        )
    if all(len(g) == 1 for g in by_pose):
        # Every image has its own pose: one camera per image (a static scene).
        chosen = ("image", by_pose, _spreads(by_pose, centers, rotations))
    else:
        # Images that share a pose: group them by what names them, by pose as a last resort.
        chosen = None
        rejected: tuple[str, str, float, float] | None = None
        candidates = []
        if all(os.path.dirname(img.name) for img in images):
            candidates.append(("folder", _groups([os.path.dirname(i.name) for i in images])))
        candidates.append(("camera_id", _groups([img.camera_id for img in images])))
        for how, groups in candidates:
            if len(groups) < 3:
                continue
            spread = _spreads(groups, centers, rotations)
            scale = _scale([centers[g].mean(axis=0) for g in groups])
            bad = [
                (d, a, g)
                for (d, a), g in zip(spread, groups, strict=True)
                if d > max_spread * scale or a > max_spread_deg
            ]
            if not bad:
                chosen = (how, groups, spread)
                break
            if rejected is None:
                d, a, g = max(bad, key=lambda x: x[0])
                label = (
                    os.path.dirname(images[g[0]].name)
                    if how == "folder"
                    else f"COLMAP camera {images[g[0]].camera_id}"
                )
                rejected = (how, label, d, a)
        if chosen is None and rejected is not None:
            how, label, d, a = rejected
            raise CalibrationError(
                f"{source}: the images of {label!r} (grouped by {how}) do not share one pose: "
                f"centres {d:.4g} from their mean, rotations {a:.3g} deg; a rig's cameras "
                "must not move"
            )
        if chosen is None:
            chosen = ("pose", by_pose, _spreads(by_pose, centers, rotations))
    assert chosen is not None
    how, groups, spread = chosen
    names = _group_names(how, groups, images)
    made: list[tuple[Camera, FisheyeLens | None]] = []
    frames: dict[str, list[str]] = {}
    spreads: dict[str, tuple[float, float]] = {}
    for name, group, (d, a) in zip(names, groups, spread, strict=True):
        cam_ids = sorted({images[k].camera_id for k in group})
        first = model.cameras[cam_ids[0]]
        for cid in cam_ids[1:]:
            other = model.cameras[cid]
            if (
                other.model != first.model
                or (other.width, other.height) != (first.width, first.height)
                or not np.allclose(other.params, first.params, rtol=1e-9, atol=1e-12)
            ):
                raise CalibrationError(
                    f"{source}: camera {name!r}: its images use COLMAP cameras {cam_ids} "
                    "with different intrinsics"
                )
        try:
            lens = colmap_fisheye(first)
            K, dist = (lens.K, lens.D) if lens is not None else colmap_intrinsics(first)
        except CalibrationError as exc:
            raise CalibrationError(f"{first.origin or source}: camera {name!r}: {exc}") from None
        if len(group) == 1:  # exactly as written
            R, t = rotations[group[0]], images[group[0]].tvec
        else:
            R = _mean_rotation([rotations[k] for k in group])
            t = -R @ centers[group].mean(axis=0)
        with in_file(source):
            made.append(
                lens_camera(
                    name, first.width, first.height, K, R, t, dist, fisheye=lens is not None
                )
            )
        frames[name] = [images[k].name for k in group]
        spreads[name] = (d, a)
    meta_up = model.meta.get("up")
    rig_up: tuple[float, ...] = (0.0, 0.0, 1.0)
    if up is not None:
        rig_up = tuple(float(v) for v in up)
    elif meta_up:
        rig_up = tuple(float(v) for v in meta_up.split(","))
    with in_file(source):
        cal = calibrated_rig(
            made,
            unit=unit if unit is not None else model.meta.get("unit", "m"),
            up=rig_up,
        )
    rig = cal.rig
    if how != "image":
        logger.info(
            "%s: %d images grouped by %s into %d cameras (largest pose spread %.3g %s, %.3g deg)",
            source,
            len(images),
            how,
            len(rig),
            max(d for d, _ in spreads.values()),
            rig.unit,
            max(a for _, a in spreads.values()),
        )
    return ColmapRig(rig=rig, frames=frames, grouping=how, pose_spread=spreads, lenses=cal.lenses)


def _strip_ext(name: str) -> str:
    base, ext = os.path.splitext(name)
    return base if ext.lower() in IMAGE_EXTENSIONS else name


def _groups(keys: Sequence[Any]) -> list[list[int]]:
    out: dict[Any, list[int]] = {}
    for k, key in enumerate(keys):
        out.setdefault(key, []).append(k)
    return list(out.values())


def _scale(centers: Iterable[NDArray[np.float64]]) -> float:
    c = np.asarray(list(centers))
    if len(c) < 2:
        return 0.0
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    return float(np.median(d[np.triu_indices(len(c), 1)]))


def _pose_groups(
    centers: NDArray[np.float64],
    rotations: list[NDArray[np.float64]],
    max_spread: float,
    max_spread_deg: float,
) -> list[list[int]]:
    """Greedy clustering: an image joins the first group whose first image is within the
    tolerances (relative to the spread of all image centres)."""
    extent = float(np.linalg.norm(centers.max(axis=0) - centers.min(axis=0))) if len(centers) else 0
    tol = max_spread * extent
    groups: list[list[int]] = []
    for k in range(len(centers)):
        for g in groups:
            ref = g[0]
            if (
                np.linalg.norm(centers[k] - centers[ref]) <= tol
                and rotation_angle_deg(rotations[k], rotations[ref]) <= max_spread_deg
            ):
                g.append(k)
                break
        else:
            groups.append([k])
    return groups


def _spreads(
    groups: list[list[int]], centers: NDArray[np.float64], rotations: list[NDArray[np.float64]]
) -> list[tuple[float, float]]:
    out = []
    for g in groups:
        C = centers[g].mean(axis=0)
        R = _mean_rotation([rotations[k] for k in g])
        d = float(np.linalg.norm(centers[g] - C, axis=1).max())
        a = max(rotation_angle_deg(rotations[k], R) for k in g)
        out.append((d, a))
    return out


def _mean_rotation(rotations: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
    """Chordal L2 mean: the rotation nearest to the sum of the matrices."""
    if len(rotations) == 1:
        return np.asarray(rotations[0], np.float64)
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    R = u @ vt
    if np.linalg.det(R) < 0:
        u[:, -1] *= -1
        R = u @ vt
    return np.asarray(R, np.float64)


def _group_names(how: str, groups: list[list[int]], images: list[ColmapImage]) -> list[str]:
    folders = [{os.path.dirname(images[k].name) for k in g} for g in groups]
    if all(len(f) == 1 and next(iter(f)) for f in folders):
        names = [next(iter(f)).replace("/", "_") for f in folders]
        if len(set(names)) == len(names):
            return names
    # One image per camera, or every image of a camera with the same file name
    # (frame000/cam0.png, frame001/cam0.png, ...): the file name.
    stems = [{_strip_ext(os.path.basename(images[k].name)) for k in g} for g in groups]
    if all(len(s) == 1 for s in stems):
        names = [next(iter(s)) for s in stems]
        if len(set(names)) == len(names):
            return names
    ids = [{images[k].camera_id for k in g} for g in groups]
    if all(len(i) == 1 for i in ids) and len({next(iter(i)) for i in ids}) == len(ids):
        return [f"cam{next(iter(i))}" for i in ids]
    return [f"cam{k}" for k in range(len(groups))]


def rig_to_colmap(
    rig: Rig,
    *,
    image_names: Sequence[str] | None = None,
    points2D: Sequence[NDArray[np.float64]] | None = None,
    point3D_ids: Sequence[NDArray[np.int64]] | None = None,
    points: ColmapPoints | None = None,
) -> ColmapModel:
    """A model with one COLMAP camera and one image per rig camera (ids 1..N in rig order),
    named ``image_names`` (default ``<camera>.png``), with optional 2D points (edgerecon
    pixel convention; shifted to COLMAP's here) and 3D points."""
    names = list(image_names) if image_names is not None else [f"{c.name}.png" for c in rig]
    if len(names) != len(rig):
        raise ValueError(f"{len(names)} image names for {len(rig)} cameras")
    cameras, images = {}, {}
    for i, cam in enumerate(rig, start=1):
        cameras[i] = camera_to_colmap(cam, i)
        uv = np.zeros((0, 2)) if points2D is None else np.asarray(points2D[i - 1], np.float64)
        ids = (
            np.zeros(0, np.int64)
            if point3D_ids is None
            else np.asarray(point3D_ids[i - 1], np.int64)
        )
        images[i] = ColmapImage(
            image_id=i,
            qvec=rotation_to_quaternion(cam.R),
            tvec=cam.t.copy(),
            camera_id=i,
            name=names[i - 1],
            points2D=uv + 0.5,
            point3D_ids=ids,
        )
    return ColmapModel(
        cameras=cameras,
        images=images,
        points3D=points if points is not None else ColmapPoints(),
        meta=rig_meta(rig),
    )


# ============================================================================== rotations
def quaternion_to_rotation(q: Sequence[float] | NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrix of a unit quaternion (w, x, y, z) (COLMAP's order)."""
    w, x, y, z = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix (Shepperd's method:
    pivot on the largest diagonal term for accuracy)."""
    m = np.asarray(R, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    cands = [tr, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 0.0))
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 0.0))
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[0] < 0 else qa


# ============================================================================== rig API
def read_colmap_rig(path: str | os.PathLike[str], *, unit: str | None = None) -> Rig:
    """The rig of a COLMAP model folder (text or binary; see ``rig_from_colmap``)."""
    return colmap_calibration(path, unit=unit).pinhole_only(find_colmap_model(path) or path)


def colmap_calibration(path: str | os.PathLike[str], *, unit: str | None = None) -> CalibratedRig:
    """``read_colmap_rig``'s rig with the lenses of its ``OPENCV_FISHEYE`` cameras."""
    folder = find_colmap_model(path)
    model = read_colmap_model(path, points=False)
    found = rig_from_colmap(model, unit=unit, source=str(folder or path))
    return CalibratedRig(rig=found.rig, lenses=found.lenses)


def write_colmap_rig(path: str | os.PathLike[str], rig: Rig, *, binary: bool = False) -> Path:
    """Write ``rig`` as a COLMAP model (one camera and one image ``<name>.png`` per rig
    camera, no 3D points) into the folder ``path``."""
    return write_colmap_model(path, rig_to_colmap(rig), binary=binary)


__all__ = [
    "CAMERA_MODELS",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "ColmapPoints",
    "ColmapRig",
    "camera_to_colmap",
    "colmap_calibration",
    "colmap_fisheye",
    "colmap_intrinsics",
    "find_colmap_model",
    "quaternion_to_rotation",
    "read_colmap_model",
    "read_colmap_rig",
    "rig_from_colmap",
    "rig_to_colmap",
    "rotation_to_quaternion",
    "write_colmap_model",
    "write_colmap_rig",
]
