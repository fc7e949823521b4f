"""Binary little-endian PLY point clouds (read by Open3D, MeshLab, CloudCompare).

Written properties: x y z (float32, or float64 with ``double=True``), nx ny nz (float32),
red green blue (uchar), label (int), confidence (float), then the extra attributes, always
with ``uchar inferred`` (1 = inferred point, e.g. ground-plane completion; 0 = measured;
``types.INFERRED``). A PLY without it reads as all measured (no attribute).
The writer records the unit and up direction as header comments (``comment unit mm``,
``comment up 0 0 -1``; ``read_ply_meta`` reads them back). A cloud of a rig far from its
world's origin (``Rig.localised``: georeferenced coordinates) is written in world
coordinates as float64 with ``comment origin X Y Z``, and ``read_ply`` gives it back
relative to that origin, the frame the rig works in (``PlyMeta.origin`` adds it back). The reader accepts any PLY: ASCII
or binary of either endianness, other elements (mesh faces) before or after the vertices,
and list properties (openMVS's per-point ``views``), which it skips; unknown scalar
properties land in ``PointCloud.attributes``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np

from edgerecon.io.records import Item, walk_records
from edgerecon.types import INFERRED, DataError, PointCloud

if TYPE_CHECKING:
    from edgerecon.geometry.camera import Rig

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_NUMPY_TO_PLY = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}


def atomic_write_bytes(path: str | os.PathLike[str], write: Any, *, sync: bool = False) -> Path:
    """Call ``write(fileobj)`` on a temporary file next to ``path``, then rename it onto
    ``path`` so readers never see a partial file. The file is 0644 less the umask (a
    temporary file is 0600); ``sync`` flushes it to disk before the rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            if sync:
                f.flush()
                os.fsync(f.fileno())
            os.fchmod(f.fileno(), 0o644 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike[str], text: str, *, sync: bool = False) -> Path:
    return atomic_write_bytes(path, lambda f: f.write(text.encode("utf-8")), sync=sync)


def _read_umask() -> int:
    mask = os.umask(0o022)  # read once at import (setting it is not thread-safe)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


@dataclass(frozen=True, kw_only=True)
class PlyMeta:
    """What a PLY header says besides its properties (edgerecon writes ``comment unit U``
    and ``comment up X Y Z``; viewers show comments as they are)."""

    unit: str | None = None
    """Length unit of the coordinates ("m", "mm", ...), None when the file does not say."""
    up: tuple[float, float, float] | None = None
    """World up direction, None when the file does not say."""
    origin: tuple[float, float, float] | None = None
    """``comment origin X Y Z``: the coordinates in the file are world coordinates and
    ``read_ply`` subtracts this (the local frame of a localised rig); None when absent."""
    crs: str | None = None
    """``comment crs TEXT``: the world frame's coordinate reference system (``Rig.crs``)."""
    comments: tuple[str, ...] = ()
    """Every comment line, in order."""
    num_vertices: int = 0
    vertex_properties: tuple[str, ...] = ()
    """Scalar vertex properties; list properties are listed as ``list:<name>``."""


def ply_comments(
    unit: str | None = None,
    up: Sequence[float] | None = None,
    origin: Sequence[float] | None = None,
    crs: str | None = None,
) -> list[str]:
    """Header comments that record a cloud's unit, up direction, (non-zero) origin and
    coordinate reference system (on one line)."""
    out = []
    if unit is not None:
        out.append(f"unit {unit}")
    if up is not None:
        out.append("up " + " ".join(repr(float(v)) for v in up))
    if origin is not None and any(origin):
        out.append("origin " + " ".join(repr(float(v)) for v in origin))
    if crs:
        out.append("crs " + " ".join(crs.encode("ascii", "replace").decode().split()))
    return out


def ply_frame(rig: Rig) -> dict[str, Any]:
    """``write_ply``'s keywords for a cloud in ``rig``'s world frame: its unit, up direction,
    origin and coordinate reference system."""
    return {"unit": rig.unit, "up": rig.up, "origin": rig.origin, "crs": rig.crs}


def write_ply(
    path: str | os.PathLike[str],
    cloud: PointCloud,
    *,
    double: bool = False,
    unit: str | None = None,
    up: Sequence[float] | None = None,
    origin: Sequence[float] | None = None,
    crs: str | None = None,
    comments: Sequence[str] = (),
) -> Path:
    """Write ``cloud`` as binary PLY, atomically. ``unit`` and ``up`` are recorded as header
    comments (``comment unit mm``, ``comment up 0 0 -1``) with any other ``comments``.
    ``origin`` (a localised rig's, non-zero): the points are relative to it; the file gets
    world coordinates (``origin`` added) as float64 and ``comment origin X Y Z``; ``crs``
    (a georeferenced rig's) as ``comment crs TEXT``.
    Every cloud gets the ``inferred`` property (all 0 when the cloud has no such attribute):
    readers can tell measured points from inferred ones in any file edgerecon writes.
    Returns the path."""
    n = len(cloud)
    if INFERRED not in cloud.attributes:
        cloud = cloud.with_inferred(False)
    fields: list[tuple[str, str]] = []
    cols: list[np.ndarray] = []
    shift = None if origin is None or not any(origin) else np.asarray(origin, np.float64)
    pos_t = "<f8" if double or shift is not None else "<f4"
    points = cloud.points3D if shift is None else cloud.points3D + shift
    for i, name in enumerate("xyz"):
        fields.append((name, pos_t))
        cols.append(points[:, i])
    if cloud.normals is not None:
        for i, name in enumerate(("nx", "ny", "nz")):
            fields.append((name, "<f4"))
            cols.append(cloud.normals[:, i])
    if cloud.colors is not None:
        for i, name in enumerate(("red", "green", "blue")):
            fields.append((name, "u1"))
            cols.append(cloud.colors[:, i])
    if cloud.labels is not None:
        fields.append(("label", "<i4"))
        cols.append(cloud.labels)
    if cloud.confidence is not None:
        fields.append(("confidence", "<f4"))
        cols.append(cloud.confidence)
    for key, value in sorted(cloud.attributes.items()):
        arr = np.asarray(value)
        code = arr.dtype.str.lstrip("<>|=")
        if code == "b1":
            arr, code = arr.astype(np.uint8), "u1"
        elif code == "i8":
            arr, code = arr.astype(np.int32), "i4"
        elif code == "u8":
            arr, code = arr.astype(np.uint32), "u4"
        if code not in _NUMPY_TO_PLY:
            raise ValueError(f"attribute {key!r}: dtype {arr.dtype} cannot be written to PLY")
        fields.append((key, ("<" if code[1] != "1" else "") + code))
        cols.append(arr)
    data = np.empty(n, dtype=np.dtype(fields))
    for (name, _), col in zip(fields, cols, strict=True):
        data[name] = col
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by edgerecon",
        *(f"comment {c}" for c in [*ply_comments(unit, up, origin, crs), *comments]),
        f"element vertex {n}",
    ]
    for name, code in fields:
        header.append(f"property {_NUMPY_TO_PLY[code.lstrip('<')]} {name}")
    header.append("end_header")
    blob = ("\n".join(header) + "\n").encode("ascii") + data.tobytes()
    return atomic_write_bytes(path, lambda f: f.write(blob))


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Read the vertex element of a PLY file into a ``PointCloud``.

    Any PLY: ASCII or binary of either endianness, other elements before or after the
    vertices (faces of a mesh), and list properties (openMVS's ``views``), which are skipped.
    A file with ``comment origin X Y Z`` is read relative to that origin (``PlyMeta.origin``).
    """
    return read_ply_with_meta(path)[0]


def read_ply_with_meta(path: str | os.PathLike[str]) -> tuple[PointCloud, PlyMeta]:
    """``read_ply`` and ``read_ply_meta`` in one read."""
    cloud, meta = _read(path)
    if meta.origin is not None:
        cloud = dataclasses.replace(cloud, points3D=cloud.points3D - np.asarray(meta.origin))
    return cloud, meta


def read_ply_meta(path: str | os.PathLike[str]) -> PlyMeta:
    """The header of a PLY file: unit, up direction, comments, vertex properties."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _parse_header(f, path)[0]
    except FileNotFoundError:
        raise DataError(f"PLY file not found: {path}") from None
    except (UnicodeDecodeError, ValueError, IndexError) as exc:
        raise DataError(f"{path}: not a readable PLY header ({exc})") from None


def _read(path: str | os.PathLike[str]) -> tuple[PointCloud, PlyMeta]:
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _read_ply(f, path)
    except FileNotFoundError:
        raise DataError(f"PLY file not found: {path}") from None
    except (UnicodeDecodeError, ValueError, IndexError) as exc:
        raise DataError(f"{path}: not a readable PLY file ({exc})") from None


# (name, count) of each element, with its properties: (name, numpy code) for scalars,
# (name, "list:<count code>:<item code>") for lists.
_Element = tuple[str, int, list[tuple[str, str]]]


def _parse_header(f: BinaryIO, path: Path) -> tuple[PlyMeta, str, list[_Element]]:
    if f.readline().strip() != b"ply":
        raise DataError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt = None
    elements: list[_Element] = []
    comments: list[str] = []
    while True:
        line = f.readline()
        if not line:
            raise DataError(f"{path}: truncated PLY header")
        text = line.decode("ascii").strip()
        words = text.split()
        if not words:
            continue
        if words[0] in ("comment", "obj_info"):
            if words[0] == "comment":
                comments.append(text[len("comment") :].strip())
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise DataError(f"{path}: property before any element")
            if words[1] == "list":
                if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                    raise DataError(f"{path}: unknown PLY type in {text!r}")
                code = f"list:{_PLY_TYPES[words[2]]}:{_PLY_TYPES[words[3]]}"
                elements[-1][2].append((words[4], code))
            else:
                if words[1] not in _PLY_TYPES:
                    raise DataError(f"{path}: unknown PLY type {words[1]!r}")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        elif words[0] == "end_header":
            break
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unsupported PLY format {fmt!r}")
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None:
        raise DataError(f"{path}: no 'vertex' element")
    unit = up = origin = crs = None
    for c in comments:
        w = c.split()
        if len(w) == 2 and w[0] == "unit":
            unit = w[1]
        elif len(w) >= 2 and w[0] == "crs":
            crs = c.split(None, 1)[1]
        elif len(w) == 4 and w[0] in ("up", "origin"):
            with contextlib.suppress(ValueError):
                vec = (float(w[1]), float(w[2]), float(w[3]))
                if w[0] == "up":
                    up = vec
                elif all(np.isfinite(vec)) and any(vec):
                    origin = vec
    meta = PlyMeta(
        unit=unit,
        up=up,
        origin=origin,
        crs=crs,
        comments=tuple(comments),
        num_vertices=vertex[1],
        vertex_properties=tuple(
            ("list:" + n if c.startswith("list:") else n) for n, c in vertex[2]
        ),
    )
    return meta, fmt, elements


def _layout(props: list[tuple[str, str]]) -> tuple[Item, ...]:
    items = []
    for _, code in props:
        if code.startswith("list:"):
            _, count, item = code.split(":")
            items.append(Item(np.dtype(item).itemsize, count_size=np.dtype(count).itemsize))
        else:
            items.append(Item(np.dtype(code).itemsize))
    return tuple(items)


def _read_ply(f: BinaryIO, path: Path) -> tuple[PointCloud, PlyMeta]:
    meta, fmt, elements = _parse_header(f, path)
    data: dict[str, np.ndarray] = {}
    if fmt == "ascii":
        for name, n, props in elements:
            rows = [f.readline() for _ in range(n)]
            if name == "vertex":
                data = _ascii_vertices(rows, props, path)
                break
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        buf = np.frombuffer(f.read(), np.uint8)
        pos = 0
        for name, n, props in elements:
            has_lists = any(code.startswith("list:") for _, code in props)
            if name == "vertex" and not has_lists:
                # The common case: fixed-size rows, read in one go.
                dtype = np.dtype([(p, endian + code) for p, code in props])
                size = dtype.itemsize * n
                if pos + size > len(buf):
                    raise DataError(
                        f"{path}: truncated PLY body ({len(buf) - pos} of {size} bytes)"
                    )
                arr = np.frombuffer(buf[pos : pos + size].tobytes(), dtype=dtype, count=n)
                data = {p: arr[p].astype(arr[p].dtype.newbyteorder("=")) for p, _ in props}
                break
            recs = walk_records(
                buf, pos, n, _layout(props), big_endian=endian == ">", what=f"{path} {name}"
            )
            if name == "vertex":
                data = {
                    p: recs.field(i, endian + code).astype(np.dtype(code).newbyteorder("="))
                    for i, (p, code) in enumerate(props)
                    if not code.startswith("list:")
                }
                break
            pos = recs.end
    for key in "xyz":
        if key not in data:
            raise DataError(f"{path}: vertex element has no {key!r} property")
    used = {"x", "y", "z"}
    pts = np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float64)
    normals = colors = labels = confidence = None
    if all(k in data for k in ("nx", "ny", "nz")):
        normals = np.stack([data["nx"], data["ny"], data["nz"]], axis=1)
        used |= {"nx", "ny", "nz"}
    for names in (
        ("red", "green", "blue"),
        ("r", "g", "b"),
        ("diffuse_red", "diffuse_green", "diffuse_blue"),
    ):
        if all(k in data for k in names):
            colors = np.stack([data[k] for k in names], axis=1)
            used |= set(names)
            break
    if "label" in data:
        labels, used = data["label"], used | {"label"}
    if "confidence" in data:
        confidence, used = data["confidence"], used | {"confidence"}
    attrs = {k: v for k, v in data.items() if k not in used}
    cloud = PointCloud(
        points3D=pts,
        colors=colors,
        normals=normals,
        labels=labels,
        confidence=confidence,
        attributes=attrs,
    )
    return cloud, meta


def _ascii_vertices(
    rows: list[bytes], props: list[tuple[str, str]], path: Path
) -> dict[str, np.ndarray]:
    n = len(rows)
    if not any(code.startswith("list:") for _, code in props):
        table = np.loadtxt(rows, ndmin=2) if n else np.zeros((0, len(props)))
        return {name: table[:, i].astype(code) for i, (name, code) in enumerate(props)}
    # Rows of different lengths: walk each row's tokens, skipping the lists.
    cols: dict[str, list[float]] = {name: [] for name, code in props if ":" not in code}
    for k, row in enumerate(rows):
        words = row.split()
        pos = 0
        try:
            for name, code in props:
                if code.startswith("list:"):
                    pos += 1 + int(words[pos])
                else:
                    cols[name].append(float(words[pos]))
                    pos += 1
        except (IndexError, ValueError):
            raise DataError(f"{path}: malformed ASCII vertex {k}") from None
    return {name: np.asarray(cols[name]).astype(code) for name, code in props if name in cols}
