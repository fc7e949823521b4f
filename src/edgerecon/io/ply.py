"""Binary little-endian PLY point clouds (read by Open3D, MeshLab, CloudCompare).

Written properties: x y z (float32, or float64 with ``double=True``), nx ny nz (float32),
red green blue (uchar), label (int), confidence (float), then any extra attributes.
The reader accepts ASCII and binary (either endianness) vertex-only PLY files with any
property names; unknown properties land in ``PointCloud.attributes``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from edgerecon.types import DataError, PointCloud

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


def write_ply(path: str | os.PathLike[str], cloud: PointCloud, *, double: bool = False) -> Path:
    """Write ``cloud`` as binary PLY, atomically. Returns the path."""
    n = len(cloud)
    fields: list[tuple[str, str]] = []
    cols: list[np.ndarray] = []
    pos_t = "<f8" if double else "<f4"
    for i, name in enumerate("xyz"):
        fields.append((name, pos_t))
        cols.append(cloud.points3D[:, i])
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
        f"element vertex {n}",
    ]
    for name, code in fields:
        header.append(f"property {_NUMPY_TO_PLY[code.lstrip('<')]} {name}")
    header.append("end_header")
    blob = ("\n".join(header) + "\n").encode("ascii") + data.tobytes()
    return atomic_write_bytes(path, lambda f: f.write(blob))


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Read the vertex element of a PLY file into a ``PointCloud``."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _read_ply(f, path)
    except FileNotFoundError:
        raise DataError(f"PLY file not found: {path}") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"{path}: not a readable PLY file ({exc})") from None


def _read_ply(f: BinaryIO, path: Path) -> PointCloud:
    if f.readline().strip() != b"ply":
        raise DataError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    while True:
        line = f.readline()
        if not line:
            raise DataError(f"{path}: truncated PLY header")
        words = line.decode("ascii").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise DataError(f"{path}: property before any element")
            if words[1] == "list":
                elements[-1][2].append((words[4], "list:" + words[2] + ":" + words[3]))
            else:
                if words[1] not in _PLY_TYPES:
                    raise DataError(f"{path}: unknown PLY type {words[1]!r}")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        elif words[0] == "end_header":
            break
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unsupported PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise DataError(f"{path}: the first PLY element must be 'vertex'")
    _, n, props = elements[0]
    if any(code.startswith("list:") for _, code in props):
        raise DataError(f"{path}: list properties in the vertex element are not supported")
    if fmt == "ascii":
        rows = [f.readline() for _ in range(n)]
        table = np.loadtxt(rows, ndmin=2) if n else np.zeros((0, len(props)))
        data = {name: table[:, i].astype(code) for i, (name, code) in enumerate(props)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, endian + code) for name, code in props])
        raw = f.read(dtype.itemsize * n)
        if len(raw) < dtype.itemsize * n:
            raise DataError(
                f"{path}: truncated PLY body ({len(raw)} of {dtype.itemsize * n} bytes)"
            )
        arr = np.frombuffer(raw, dtype=dtype, count=n)
        data = {name: arr[name].astype(arr[name].dtype.newbyteorder("=")) for name, _ in props}
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
    return PointCloud(
        points3D=pts,
        colors=colors,
        normals=normals,
        labels=labels,
        confidence=confidence,
        attributes=attrs,
    )
