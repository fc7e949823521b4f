"""Progress reporting for long operations.

Library code wraps long loops in :func:`track`; it is silent unless the CLI (or a user) turns
progress display on with :func:`enable`. Keeping the switch here, rather than passing a
callback through every stage, keeps the pure stage signatures free of UI concerns.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")

_enabled = False
_depth = 0  # rich allows one live display at a time: nested loops run without their own bar


def enable(on: bool = True) -> None:
    """Show rich progress bars for long operations (the CLI does this on a terminal)."""
    global _enabled
    _enabled = on


def enabled() -> bool:
    return _enabled


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate over ``items``, showing a transient progress bar when enabled."""
    global _depth
    if not _enabled or _depth > 0:
        yield from items
        return
    from rich.progress import Progress

    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    _depth += 1
    try:
        with Progress(transient=True) as progress:
            task = progress.add_task(description, total=total)
            for item in items:
                yield item
                progress.advance(task)
    finally:
        _depth -= 1
