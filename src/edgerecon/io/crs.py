"""A georeferenced rig's coordinate reference system (CRS), checked with pyproj.

A rig calibrated in a surveyed frame (UTM, a national grid, ECEF) has world coordinates in
a CRS the user knows and edgerecon cannot guess: ``edgerecon import --crs EPSG:32633`` (or
``export --crs``) records it (``Rig.crs``, in rig.json), and LAS / LAZ exports carry it as
the OGC WKT record LAS 1.4 asks for, so that QGIS, PDAL and CloudCompare place the cloud on
the map. edgerecon works in Cartesian lengths and writes LAS in metres: the CRS must be
projected or geocentric with metre axes (a geographic CRS in degrees, or one in feet, is
refused with the reason).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from edgerecon.types import DataError

if TYPE_CHECKING:
    import pyproj


def check_crs(text: str) -> pyproj.CRS:
    """The CRS ``text`` names (``EPSG:32633``, ``32633``, WKT, a PROJ string), checked to
    be usable as a rig's world frame; DataError with the reason otherwise."""
    import pyproj
    from pyproj.exceptions import CRSError

    spec = text.strip()
    if spec.isdigit():  # a bare EPSG code
        spec = f"EPSG:{spec}"
    try:
        crs = pyproj.CRS.from_user_input(spec)
    except CRSError as exc:
        raise DataError(f"{text!r} is not a coordinate reference system ({exc})") from None
    horizontal = crs.sub_crs_list[0] if crs.is_compound and crs.sub_crs_list else crs
    if horizontal.is_geographic and not horizontal.is_geocentric:
        raise DataError(
            f"{crs.name} is geographic (latitude / longitude in degrees): a rig's world frame "
            "is Cartesian; give a projected CRS (UTM, a national grid) or a geocentric one "
            "(ECEF, EPSG:4978)"
        )
    units = {a.unit_name for a in horizontal.axis_info}
    if units and units != {"metre"}:
        raise DataError(
            f"{crs.name} measures in {', '.join(sorted(units))}: edgerecon writes LAS in "
            "metres, give the metre variant of this CRS"
        )
    return crs


def crs_name(text: str | None) -> str | None:
    """The CRS's name for messages ("WGS 84 / UTM zone 33N"), None without one."""
    return None if not text else str(check_crs(text).name)


__all__ = ["check_crs", "crs_name"]
