"""Point clouds as ASPRS LAS 1.4 / LAZ, the format of GIS and survey tools (QGIS, ArcGIS,
PDAL, Potree, CloudCompare, LAStools), through laspy (LAZ compression: lazrs).

A cloud is written as point format 7: coordinates as 32-bit integers of a millimetre about
an offset (the cloud's origin, so that a georeferenced rig's UTM or ECEF coordinates keep
their millimetres; the cloud's centre when it is far from its origin), 16-bit RGB, and
what edgerecon knows of each point: classification 64 (the first class LAS 1.4 leaves to
users) for the foreground, 1 (unclassified) for the rest,
the object label in ``user_data`` (0: background; labels above 255 are clipped), and the
*synthetic* flag for points no stereo depth measured (``PointCloud.inferred``, the floor's
completion). LAS records no unit of length: coordinates are written in metres (the rig's
unit converted), and the header's generating software names edgerecon. A georeferenced
rig's coordinate reference system (``Rig.crs``, ``--crs``) is written as LAS 1.4's OGC WKT
record (``io.crs`` checks it: metres, Cartesian); without one the file has none.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgerecon.io.crs import check_crs
from edgerecon.io.export import METRES_PER_UNIT
from edgerecon.io.ply import atomic_write_bytes
from edgerecon.types import INFERRED, DataError, PointCloud

#: The classification of foreground points (LAS 1.4: 64-255 are user-definable).
FOREGROUND_CLASS = 64
#: LAS coordinates' quantum, metres.
SCALE_M = 0.001


def metres_per(unit: str | None) -> float:
    """Metres per ``unit`` (None: the coordinates are taken as metres)."""
    if unit is None:
        return 1.0
    try:
        return METRES_PER_UNIT[unit.lower()]
    except KeyError:
        raise DataError(
            f"unit {unit!r} is not one edgerecon converts to metres ({', '.join(METRES_PER_UNIT)})"
        ) from None


def write_las(
    path: str | os.PathLike[str],
    cloud: PointCloud,
    *,
    unit: str | None,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    crs: str | None = None,
) -> Path:
    """Write ``cloud`` (local coordinates in ``unit`` about ``origin``, the rig's) as LAS,
    or LAZ when ``path`` ends in ``.laz``; atomically; ``crs``: the world frame's coordinate
    reference system (a WKT record). Returns the path."""
    import laspy

    path = Path(path)
    checked = None if not crs else check_crs(crs)
    m = metres_per(unit)
    origin_m = np.asarray(origin, np.float64).reshape(3) * m
    n = len(cloud)
    xyz = cloud.points3D * m + origin_m
    offsets = np.round(origin_m, 3)

    def fits(offsets: np.ndarray) -> bool:
        return not n or bool(np.all(np.abs((xyz - offsets) / SCALE_M) < 2**31 - 1))

    if not fits(offsets):  # world coordinates given about zero (a UTM cloud): its own centre
        offsets = np.round((xyz.min(axis=0) + xyz.max(axis=0)) / 2)
        if not fits(offsets):
            raise DataError(f"{path}: the cloud spans more than 2,000 km: LAS cannot hold it")
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.full(3, SCALE_M)
    header.offsets = offsets
    header.generating_software = "edgerecon"
    if checked is not None:
        header.add_crs(checked)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if cloud.colors is not None:
        rgb = cloud.colors.astype(np.uint16) * 257  # 8 to 16 bits: 255 -> 65535
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    labels = np.zeros(n, np.int64) if cloud.labels is None else cloud.labels.astype(np.int64)
    las.classification = np.where(labels > 0, FOREGROUND_CLASS, 1).astype(np.uint8)
    las.user_data = np.clip(labels, 0, 255).astype(np.uint8)
    las.synthetic = cloud.inferred
    compress = path.suffix.lower() == ".laz"
    buffer = io.BytesIO()
    las.write(buffer, do_compress=compress)
    return atomic_write_bytes(path, lambda f: f.write(buffer.getbuffer()))


def read_las(path: str | os.PathLike[str]) -> tuple[PointCloud, dict[str, object]]:
    """A LAS / LAZ file as a cloud in metres (world coordinates) and what its header says
    (``generating_software``, ``point_format``, ``version``, ``crs``: the name of its
    coordinate reference system or None, ``crs_wkt``: its WKT); labels from ``user_data``,
    inferred from the synthetic flag."""
    import laspy

    try:
        las = laspy.read(path)
    except (OSError, laspy.LaspyException) as exc:
        raise DataError(f"{path}: not a readable LAS / LAZ file ({exc})") from None
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
    names = set(las.point_format.dimension_names)
    colors = None
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], 1)
        colors = (rgb // 257).astype(np.uint8)
    cloud = PointCloud(
        points3D=xyz,
        colors=colors,
        labels=np.asarray(las.user_data).astype(np.int32),
        attributes={INFERRED: np.asarray(las.synthetic).astype(np.uint8)},
    )
    info: dict[str, object] = {
        "generating_software": las.header.generating_software,
        "point_format": las.header.point_format.id,
        "version": str(las.header.version),
        "classification": np.asarray(las.classification).astype(np.uint8),
        **_crs_of(las.header),
    }
    return cloud, info


def _crs_of(header: object) -> dict[str, str | None]:
    """The name and WKT of the CRS a LAS header records (WKT or GeoTIFF keys), None
    without one."""
    try:
        crs = header.parse_crs()  # type: ignore[attr-defined]
    except Exception:  # an unreadable record is no CRS, not a bad file
        crs = None
    if crs is None:
        return {"crs": None, "crs_wkt": None}
    return {"crs": str(crs.name), "crs_wkt": str(crs.to_wkt())}


__all__ = ["FOREGROUND_CLASS", "SCALE_M", "metres_per", "read_las", "write_las"]
