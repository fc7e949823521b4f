"""Binary records of variable length (PLY rows with list properties, COLMAP's points3D.bin
tracks), located with one compiled pass and gathered with NumPy.

A record layout is a sequence of items; each item is either a fixed field of ``size`` bytes
or a list: a count of ``count_size`` bytes followed by that many entries of ``size`` bytes.
Where a row starts depends on the counts of every row before it, which is a sequential walk:
it runs in numba (one pass over the counts, ~10 ms per million rows), and everything else
(gathering the fixed fields and the list entries) is vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from edgerecon.types import DataError


@dataclass(frozen=True)
class Item:
    """One item of a record layout: a fixed field (``count_size == 0``) or a list."""

    size: int
    """Bytes of the field, or of one list entry."""
    count_size: int = 0
    """Bytes of the list's count (1, 2, 4 or 8); 0 for a fixed field."""


@nb.njit(cache=True, nogil=True)
def _walk(
    buf: NDArray[np.uint8],
    start: int,
    num_rows: int,
    sizes: NDArray[np.int64],
    count_sizes: NDArray[np.int64],
    big_endian: bool,
    offsets: NDArray[np.int64],
    counts: NDArray[np.int64],
) -> int:
    """Fill ``offsets[r, i]`` (byte offset of item i of row r) and ``counts[r, i]`` (list
    length, 1 for fixed fields); return the offset after the last row, or -1 when the buffer
    ends inside a row."""
    pos = start
    n = buf.shape[0]
    num_items = sizes.shape[0]
    for r in range(num_rows):
        for i in range(num_items):
            offsets[r, i] = pos
            cs = count_sizes[i]
            if cs == 0:
                counts[r, i] = 1
                pos += sizes[i]
            else:
                if pos + cs > n:
                    return -1
                c = 0
                for b in range(cs):
                    byte = buf[pos + (b if big_endian else cs - 1 - b)]
                    c = c * 256 + byte
                counts[r, i] = c
                pos += cs + c * sizes[i]
            if pos > n:
                return -1
    return pos


@dataclass(frozen=True, eq=False)
class Records:
    """Where the items of ``num_rows`` records lie in a buffer."""

    buf: NDArray[np.uint8]
    offsets: NDArray[np.int64]
    """(rows, items) byte offset of each item (of a list: of its count)."""
    counts: NDArray[np.int64]
    """(rows, items) list lengths (1 for fixed fields)."""
    layout: tuple[Item, ...]
    end: int
    """Byte offset right after the last record."""

    def field(
        self, item: int, dtype: np.dtype[np.generic] | str, at: int = 0
    ) -> NDArray[np.generic]:
        """(rows,) values of a fixed field (or a part of it starting ``at`` bytes in)."""
        dt = np.dtype(dtype)
        starts = self.offsets[:, item] + at
        return self._gather(starts, dt)

    def list_entries(
        self, item: int, dtype: np.dtype[np.generic] | str
    ) -> tuple[NDArray[np.generic], NDArray[np.int64]]:
        """All entries of list ``item`` concatenated over the rows, and the (rows + 1,)
        offsets of each row's entries in that array."""
        dt = np.dtype(dtype)
        lay = self.layout[item]
        counts = self.counts[:, item]
        row_starts = np.zeros(len(counts) + 1, np.int64)
        np.cumsum(counts, out=row_starts[1:])
        total = int(row_starts[-1])
        if total == 0:
            return np.zeros(0, dt), row_starts
        rows = np.repeat(np.arange(len(counts)), counts)
        within = np.arange(total) - row_starts[rows]
        starts = self.offsets[rows, item] + lay.count_size + within * lay.size
        return self._gather(starts, dt), row_starts

    def _gather(self, starts: NDArray[np.int64], dt: np.dtype[np.generic]) -> NDArray[np.generic]:
        if len(starts) == 0:
            return np.zeros(0, dt)
        idx = starts[:, None] + np.arange(dt.itemsize)
        return np.ascontiguousarray(self.buf[idx]).view(dt).reshape(len(starts))


def walk_records(
    buf: NDArray[np.uint8] | bytes,
    start: int,
    num_rows: int,
    layout: tuple[Item, ...],
    *,
    big_endian: bool = False,
    what: str = "records",
) -> Records:
    """Locate ``num_rows`` records of ``layout`` in ``buf`` from byte ``start``. Raises
    ``DataError`` naming ``what`` when the buffer ends inside a record."""
    arr = np.frombuffer(buf, np.uint8) if isinstance(buf, bytes | bytearray) else buf
    for it in layout:
        if it.count_size not in (0, 1, 2, 4, 8) or it.size < 0:
            raise ValueError(f"bad record item {it}")
    sizes = np.array([it.size for it in layout], np.int64)
    count_sizes = np.array([it.count_size for it in layout], np.int64)
    offsets = np.zeros((num_rows, len(layout)), np.int64)
    counts = np.zeros((num_rows, len(layout)), np.int64)
    if not any(count_sizes):
        # Fixed-size rows: no walk needed.
        row = int(sizes.sum())
        offsets[:] = (
            start
            + np.arange(num_rows)[:, None] * row
            + np.concatenate([[0], np.cumsum(sizes)[:-1]])
        )
        counts[:] = 1
        end = start + row * num_rows
        if end > len(arr):
            raise DataError(f"{what}: truncated ({len(arr) - start} of {end - start} bytes)")
    else:
        end = int(_walk(arr, start, num_rows, sizes, count_sizes, big_endian, offsets, counts))
        if end < 0:
            raise DataError(f"{what}: truncated (the data ends inside a record)")
    return Records(buf=arr, offsets=offsets, counts=counts, layout=layout, end=end)


__all__ = ["Item", "Records", "walk_records"]
