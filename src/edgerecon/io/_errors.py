"""Error helpers shared by the readers."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from edgerecon.types import CalibrationError


@contextlib.contextmanager
def in_file(path: Path | str) -> Iterator[None]:
    """Prefix CalibrationErrors raised inside (e.g. by Camera/Rig validation) with a file."""
    try:
        yield
    except CalibrationError as exc:
        msg = str(exc)
        if str(path) in msg:
            raise
        raise CalibrationError(f"{path}: {msg}") from None
