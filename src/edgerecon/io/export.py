"""Exports to the tools people use: COLMAP models (with 3D points and their tracks, as
openMVS's ``InterfaceCOLMAP`` and COLMAP's own tools read them) and viewer-friendly PLY.

* ``export_colmap`` writes COLMAP's *undistorted workspace* layout: ``images/<camera>.png``
  (the frames of one timestamp, undistorted to ideal pinhole cameras) and ``sparse/``
  (``cameras``, ``images``, ``points3D`` in text or binary) with PINHOLE cameras; openMVS
  imports it with ``InterfaceCOLMAP -i OUT -o scene.mvs``. ``distorted=True`` writes the
  original frames with OPENCV cameras instead (for COLMAP's own tools).
* Tracks: a 3D point is listed in the images where it projects inside the frame and is not
  hidden behind the scene (``visibility_tracks``: a depth test against a z-buffer of the
  occluding cloud, by default the dense cloud of the same reconstruction; 2 % of the depth
  tolerance, each occluder covering 3 x 3 pixels). Its 2D point is its projection. Points seen by fewer than
  ``min_track`` images are left out (COLMAP and openMVS need two views).
* ``z_up_metres``: a similarity (scale to metres, rotation taking the rig's up to +Z) for
  viewers that assume Z-up metres; it applies to the cloud and the camera poses alike, so a
  model stays consistent.
* ``export_nerfstudio`` writes nerfstudio's data layout: ``images/<camera>.png`` (undistorted),
  ``transforms.json`` (per-frame pinhole intrinsics, OpenGL camera-to-world poses; also what
  Instant-NGP reads) and ``points3D.ply``, named by ``ply_file_path``, which nerfstudio's
  Gaussian splatting (``splatfacto``) starts from.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.geometry.lens import FisheyeLens
from edgerecon.io.calib_nerf import write_transforms
from edgerecon.io.colmap import ColmapCamera, ColmapPoints, rig_to_colmap, write_colmap_model
from edgerecon.io.ply import atomic_write_bytes, ply_frame, write_ply
from edgerecon.types import DataError, FrameSet, PointCloud, Points3D

logger = logging.getLogger(__name__)

#: Metres per unit of the units edgerecon knows.
METRES_PER_UNIT = {
    "m": 1.0,
    "dm": 0.1,
    "cm": 0.01,
    "mm": 0.001,
    "um": 1e-6,
    "km": 1000.0,
    "in": 0.0254,
    "ft": 0.3048,
}


# ============================================================================== transforms
@dataclass(frozen=True, kw_only=True)
class Similarity:
    """``X' = scale * R @ X``: a change of world frame and unit."""

    scale: float
    R: NDArray[np.float64]
    unit: str
    """Unit after the transform."""
    up: tuple[float, float, float]
    """Up direction after the transform."""

    def points(self, pts: Points3D) -> Points3D:
        return np.asarray(self.scale * (np.asarray(pts, np.float64) @ self.R.T), np.float64)

    def cloud(self, cloud: PointCloud) -> PointCloud:
        normals = None if cloud.normals is None else cloud.normals @ self.R.T.astype(np.float32)
        return PointCloud(
            points3D=self.points(cloud.points3D),
            colors=cloud.colors,
            normals=normals,
            labels=cloud.labels,
            confidence=cloud.confidence,
            attributes=dict(cloud.attributes),
        )

    def camera(self, cam: Camera) -> Camera:
        # X_cam = R X + t = R R_s^T X' / s + t; scaling the camera frame by s keeps pixels.
        return Camera(
            name=cam.name,
            width=cam.width,
            height=cam.height,
            K=cam.K,
            R=cam.R @ self.R.T,
            t=self.scale * cam.t,
            dist=cam.dist,
        )

    def rig(self, rig: Rig) -> Rig:
        origin = self.points(np.asarray([rig.origin], np.float64))[0]
        return Rig(
            cameras=tuple(self.camera(c) for c in rig),
            unit=self.unit,
            up=self.up,
            origin=(float(origin[0]), float(origin[1]), float(origin[2])),
        )

    def describe(self) -> str:
        return (
            f"scaled by {self.scale:g} to {self.unit}, rotated so that up is "
            f"({', '.join(f'{v:g}' for v in self.up)})"
        )


def rotation_between(a: Sequence[float], b: Sequence[float]) -> NDArray[np.float64]:
    """The smallest rotation taking direction ``a`` to direction ``b``."""
    u = np.asarray(a, np.float64) / np.linalg.norm(a)
    v = np.asarray(b, np.float64) / np.linalg.norm(b)
    axis = np.cross(u, v)
    s, c = float(np.linalg.norm(axis)), float(u @ v)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite: half a turn about any axis orthogonal to u.
        ortho = np.cross(u, [1.0, 0, 0] if abs(u[0]) < 0.9 else [0, 1.0, 0])
        ortho /= np.linalg.norm(ortho)
        return np.asarray(cv2.Rodrigues(ortho * math.pi)[0], np.float64)
    return np.asarray(cv2.Rodrigues(axis / s * math.atan2(s, c))[0], np.float64)


def z_up_metres(unit: str, up: Sequence[float]) -> Similarity:
    """The similarity from a world in ``unit`` with ``up`` to metres with up along +Z
    (e.g. ``z_up_metres(rig.unit, rig.up)``)."""
    if unit.lower() not in METRES_PER_UNIT:
        raise DataError(
            f"unit {unit!r} is not one edgerecon converts to metres ({', '.join(METRES_PER_UNIT)})"
        )
    return Similarity(
        scale=METRES_PER_UNIT[unit.lower()],
        R=rotation_between(up, (0.0, 0.0, 1.0)),
        unit="m",
        up=(0.0, 0.0, 1.0),
    )


# ============================================================================== tracks
@dataclass(frozen=True, kw_only=True, eq=False)
class Tracks:
    """Which points each camera sees, and where."""

    point_ids: list[NDArray[np.int64]]
    """Per camera: indices of the points it sees."""
    points2D: list[NDArray[np.float64]]
    """Per camera: (M, 2) projections of those points (edgerecon pixel convention)."""

    def lengths(self, num_points: int) -> NDArray[np.int64]:
        n = np.zeros(num_points, np.int64)
        for ids in self.point_ids:
            n[ids] += 1
        return n


def visibility_tracks(
    points3D: Points3D,
    cameras: Sequence[Camera],
    *,
    occluders: Points3D | None = None,
    zbuffer_scale: float = 1.0,
    depth_tolerance: float = 0.02,
) -> Tracks:
    """Per camera, the points that project inside its image and lie no more than
    ``depth_tolerance`` (relative) behind the nearest occluder in their z-buffer cell
    (``occluders``: the surface that hides things, default the points themselves)."""
    from edgerecon.scene.hull import depth_map

    pts = np.asarray(points3D, np.float64).reshape(-1, 3)
    occ = pts if occluders is None else np.asarray(occluders, np.float64).reshape(-1, 3)
    ids_out, uv_out = [], []
    for cam in cameras:
        uv, depth = cam.project(pts)
        inside = np.flatnonzero((depth > 0) & cam.in_image(uv))
        small = cam.scaled(zbuffer_scale)
        zmap = depth_map(occ, small, fill_px=1) if len(occ) else None
        if zmap is not None and len(inside):
            uvs, _ = small.project(pts[inside])
            u = np.clip(np.rint(uvs[:, 0]).astype(np.intp), 0, small.width - 1)
            v = np.clip(np.rint(uvs[:, 1]).astype(np.intp), 0, small.height - 1)
            z = zmap[v, u].astype(np.float64)
            with np.errstate(invalid="ignore", over="ignore"):
                visible = ~np.isfinite(z) | (depth[inside] <= z * (1 + depth_tolerance))
            inside = inside[visible]
        ids_out.append(inside.astype(np.int64))
        uv_out.append(uv[inside])
    return Tracks(point_ids=ids_out, points2D=uv_out)


# ============================================================================== COLMAP
@dataclass(frozen=True, kw_only=True)
class ExportReport:
    """What ``export_colmap`` wrote."""

    folder: Path
    model: Path
    images: list[Path]
    num_points_in: int
    num_points: int
    """Points written (seen by at least ``min_track`` images)."""
    mean_track_length: float
    observations_per_image: dict[str, int]
    distorted: bool
    binary: bool
    transform: str | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "folder": str(self.folder),
            "model": str(self.model),
            "images": [str(p) for p in self.images],
            "num_points_in": self.num_points_in,
            "num_points": self.num_points,
            "mean_track_length": self.mean_track_length,
            "observations_per_image": self.observations_per_image,
            "distorted": self.distorted,
            "binary": self.binary,
            "transform": self.transform,
        }


def export_colmap(
    out: str | os.PathLike[str],
    rig: Rig,
    cloud: PointCloud,
    *,
    frames: FrameSet | None = None,
    occluders: PointCloud | None = None,
    distorted: bool = False,
    binary: bool = False,
    min_track: int = 2,
    image_ext: str = ".png",
    transform: Similarity | None = None,
    model_dir: str = "sparse",
    lenses: Mapping[str, FisheyeLens] | None = None,
) -> ExportReport:
    """Write ``cloud`` and the rig's cameras as a COLMAP workspace in ``out`` (see the
    module docstring). ``frames`` (the timestamp's frames, in rig order) become
    ``images/``; without them only the model is written, in ``out/<model_dir>`` (``sparse``
    for openMVS and COLMAP, ``sparse/0`` where 3D Gaussian Splatting and nerfstudio look).
    ``transform`` (e.g. ``z_up_metres(rig.unit, rig.up)``) changes the world frame of the
    cloud and the poses alike. With ``distorted``, ``lenses`` (the fisheye cameras', whose
    rig cameras are their rectified views): those cameras are written as COLMAP's
    ``OPENCV_FISHEYE`` with their points' pixels in the frames as filmed (``frames`` must
    then be those, not the rectified ones)."""
    out = Path(out)
    if Path(model_dir).is_absolute() or ".." in Path(model_dir).parts:
        raise DataError(f"the model's folder must be inside the workspace, got {model_dir!r}")
    if min_track < 1:
        raise ValueError(f"min_track must be >= 1, got {min_track}")
    if transform is not None:
        rig, cloud = transform.rig(rig), transform.cloud(cloud)
        occluders = None if occluders is None else transform.cloud(occluders)
    cams = list(rig) if distorted else [c.undistorted() for c in rig]
    tracks = visibility_tracks(
        cloud.points3D,
        cams,
        occluders=None if occluders is None else occluders.points3D,
    )
    lengths = tracks.lengths(len(cloud))
    keep = lengths >= min_track
    new_id = np.full(len(cloud), -1, np.int64)
    new_id[keep] = np.arange(1, int(keep.sum()) + 1)
    # Per image: only the observations of kept points; POINT2D_IDX = position in the image.
    uv_per_image, ids_per_image = [], []
    obs_point, obs_image, obs_idx = [], [], []
    for k, (ids, uv) in enumerate(zip(tracks.point_ids, tracks.points2D, strict=True)):
        m = keep[ids]
        ids, uv = ids[m], uv[m]
        uv_per_image.append(uv)
        ids_per_image.append(new_id[ids])
        obs_point.append(new_id[ids])
        obs_image.append(np.full(len(ids), k + 1, np.int64))
        obs_idx.append(np.arange(len(ids), dtype=np.int64))
    p_all = np.concatenate(obs_point) if obs_point else np.zeros(0, np.int64)
    order = np.lexsort((np.concatenate(obs_image), p_all)) if len(p_all) else np.zeros(0, int)
    counts = np.bincount(p_all, minlength=int(keep.sum()) + 1)[1:]
    offsets = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    kept = cloud.select(keep)
    colors = kept.colors if kept.colors is not None else np.full((len(kept), 3), 128, np.uint8)
    points = ColmapPoints(
        ids=np.arange(1, len(kept) + 1, dtype=np.int64),
        xyz=kept.points3D + np.asarray(rig.origin),  # world coordinates (Rig.localised)
        rgb=colors,
        error=np.zeros(len(kept)),
        track_offsets=offsets,
        track_image_ids=np.concatenate(obs_image)[order] if len(p_all) else np.zeros(0, np.int64),
        track_point2D_idxs=np.concatenate(obs_idx)[order] if len(p_all) else np.zeros(0, np.int64),
    )
    export_rig = Rig(
        cameras=tuple(cams), unit=rig.unit, up=rig.up, origin=rig.origin, min_cameras=1
    ).in_world()
    names = [f"{c.name}{image_ext}" for c in cams]
    fisheye = dict(lenses or {}) if distorted else {}
    for k, cam in enumerate(cams):  # the points' pixels in the frames as filmed
        if cam.name in fisheye:
            uv_per_image[k] = fisheye[cam.name].from_pinhole(cam.K, uv_per_image[k])
    model = rig_to_colmap(
        export_rig,
        image_names=names,
        points2D=uv_per_image,
        point3D_ids=ids_per_image,
        points=points,
    )
    for k, cam in enumerate(cams, start=1):
        if cam.name in fisheye:
            lens = fisheye[cam.name]
            fx, fy, cx, cy = lens.K[0, 0], lens.K[1, 1], lens.K[0, 2] + 0.5, lens.K[1, 2] + 0.5
            model.cameras[k] = ColmapCamera(
                camera_id=k,
                model="OPENCV_FISHEYE",
                width=lens.width,
                height=lens.height,
                params=np.array([fx, fy, cx, cy, *lens.D], np.float64),
            )
    written = write_colmap_model(out / model_dir, model, binary=binary)
    images = [] if frames is None else _write_frames(out, list(rig), frames, names, distorted)
    return ExportReport(
        folder=out,
        model=written,
        images=images,
        num_points_in=len(cloud),
        num_points=len(kept),
        mean_track_length=float(counts.mean()) if len(counts) else 0.0,
        observations_per_image={
            c.name: len(ids) for c, ids in zip(cams, ids_per_image, strict=True)
        },
        distorted=distorted,
        binary=binary,
        transform=None if transform is None else transform.describe(),
    )


# ============================================================================== nerfstudio
@dataclass(frozen=True, kw_only=True)
class NerfstudioReport:
    """What ``export_nerfstudio`` wrote."""

    folder: Path
    transforms: Path
    images: list[Path]
    ply: Path
    num_points: int
    transform: str | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "folder": str(self.folder),
            "transforms": str(self.transforms),
            "images": [str(p) for p in self.images],
            "ply": str(self.ply),
            "num_points": self.num_points,
            "transform": self.transform,
        }


def _write_frames(
    out: Path, cams: Sequence[Camera], frames: FrameSet, names: Sequence[str], distorted: bool
) -> list[Path]:
    """The timestamp's frames as ``out/images/<name>`` (undistorted unless ``distorted``;
    ``cams`` are the rig's own cameras, in its order)."""
    if len(frames.images) != len(cams):
        raise DataError(f"{len(frames.images)} frames for a rig of {len(cams)} cameras")
    images = []
    for cam, name, image in zip(cams, names, frames.images, strict=True):
        if image is None:
            raise DataError(f"camera {cam.name!r} has no frame at time {frames.time_index}")
        picture = image if distorted else cam.prepare_image(image)
        ok, data = cv2.imencode(Path(name).suffix, picture)
        if not ok:
            raise DataError(f"cannot encode {name}")
        images.append(
            atomic_write_bytes(out / "images" / name, lambda f, d=data: f.write(d.tobytes()))
        )
    return images


def export_nerfstudio(
    out: str | os.PathLike[str],
    rig: Rig,
    cloud: PointCloud,
    frames: FrameSet,
    *,
    transform: Similarity | None = None,
    image_ext: str = ".png",
) -> NerfstudioReport:
    """Write one timestamp as a nerfstudio dataset in ``out`` (see the module docstring):
    ``frames`` (in rig order) undistorted, the cameras as pinhole cameras in world
    coordinates, ``cloud`` as the splats' starting points. ``transform`` (e.g.
    ``z_up_metres``) changes the world frame of the cloud and the poses alike."""
    out = Path(out)
    if transform is not None:
        rig, cloud = transform.rig(rig), transform.cloud(cloud)
    names = [f"{c.name}{image_ext}" for c in rig]
    images = _write_frames(out, list(rig), frames, names, distorted=False)
    world = Rig(
        cameras=tuple(c.undistorted() for c in rig),
        unit=rig.unit,
        up=rig.up,
        origin=rig.origin,
        crs=rig.crs,
        min_cameras=1,
    ).in_world()
    ply = write_ply(
        out / "points3D.ply",
        cloud,
        **ply_frame(rig),
        comments=["exported by edgerecon for nerfstudio"],
    )
    written = write_transforms(
        out / "transforms.json",
        world,
        {c.name: f"images/{n}" for c, n in zip(rig, names, strict=True)},
        ply_file_path=ply.name,
    )
    return NerfstudioReport(
        folder=out,
        transforms=written,
        images=images,
        ply=ply,
        num_points=len(cloud),
        transform=None if transform is None else transform.describe(),
    )


__all__ = [
    "METRES_PER_UNIT",
    "ExportReport",
    "NerfstudioReport",
    "Similarity",
    "Tracks",
    "export_colmap",
    "export_nerfstudio",
    "rotation_between",
    "visibility_tracks",
    "z_up_metres",
]
