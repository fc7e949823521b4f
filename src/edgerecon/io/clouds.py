"""Point-cloud files of any format edgerecon reads: PLY (``io.ply``) and LAS / LAZ
(``io.las``: a laser scan of the site, a survey's cloud), with the unit and origin their
coordinates are in, and the conversion of one into another's unit (and coordinate
reference system)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from edgerecon.io.crs import check_crs
from edgerecon.io.las import metres_per, read_las
from edgerecon.io.ply import read_ply, read_ply_meta
from edgerecon.types import DataError, PointCloud

#: File suffixes read as LAS.
LAS_SUFFIXES = (".las", ".laz")


@dataclasses.dataclass(frozen=True, eq=False)
class CloudFile:
    """A cloud as read, its points relative to ``origin`` (None: world coordinates)."""

    cloud: PointCloud
    unit: str | None
    """The coordinates' unit, None when the file does not say."""
    origin: tuple[float, float, float] | None
    crs: str | None = None
    """The coordinate reference system of its world coordinates (LAS's record, a PLY's
    ``comment crs``), None when the file does not say."""

    def reprojected(self, crs: str | None) -> CloudFile:
        """The cloud in ``crs`` (pyproj), when both CRSs are known and differ (a laser scan
        in a national grid against a rig in UTM); else itself. Both are metre CRSs
        (``io.crs``): the coordinates go through in metres."""
        if not crs or not self.crs:
            return self
        import pyproj

        src, dst = check_crs(self.crs), check_crs(crs)
        if src.equals(dst, ignore_axis_order=True):
            return self
        m = metres_per(self.unit)
        origin = np.asarray(self.origin or (0.0, 0.0, 0.0), np.float64)
        xyz = (self.cloud.points3D.astype(np.float64) + origin) * m
        move = pyproj.Transformer.from_crs(src, dst, always_xy=True)
        x, y, z = move.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
        out = np.stack([x, y, z], axis=1) / m
        if not np.all(np.isfinite(out)):
            raise DataError(f"{src.name} -> {dst.name}: some points cannot be transformed")
        return dataclasses.replace(
            self,
            cloud=dataclasses.replace(self.cloud, points3D=out - origin),
            crs=crs,
        )

    def world(self, unit: str | None = None) -> tuple[PointCloud, tuple[float, float, float]]:
        """The cloud (relative to the returned origin) converted to ``unit`` (None, or an
        unknown unit on either side: as it is)."""
        factor = 1.0
        if unit is not None and self.unit is not None and unit != self.unit:
            factor = metres_per(self.unit) / metres_per(unit)
        origin = np.asarray(self.origin or (0.0, 0.0, 0.0), np.float64) * factor
        cloud = self.cloud
        if factor != 1.0:
            cloud = dataclasses.replace(cloud, points3D=cloud.points3D * factor)
        return cloud, (float(origin[0]), float(origin[1]), float(origin[2]))


def read_cloud_file(path: str | os.PathLike[str]) -> CloudFile:
    """A PLY (its header's unit and origin) or a LAS / LAZ file (metres, world
    coordinates)."""
    if Path(path).suffix.lower() in LAS_SUFFIXES:
        cloud, info = read_las(path)
        wkt = info["crs_wkt"]
        return CloudFile(cloud=cloud, unit="m", origin=None, crs=str(wkt) if wkt else None)
    meta = read_ply_meta(path)
    return CloudFile(cloud=read_ply(path), unit=meta.unit, origin=meta.origin, crs=meta.crs)


__all__ = ["LAS_SUFFIXES", "CloudFile", "read_cloud_file"]
