"""Failed-task reasons (runtime.messages.describe_exception)."""

from __future__ import annotations

from pathlib import Path

import pytest

from edgerecon.runtime.messages import describe_exception
from edgerecon.threads import thread_map


def test_the_location_is_the_innermost_frame_of_the_package(tmp_path: Path) -> None:
    # A file outside the package whose path holds the package's name (a clone in
    # ~/edgerecon keeps its virtual environment and tests there) is not the product's frame.
    outside = tmp_path / "edgerecon" / ".venv" / "helper.py"
    outside.parent.mkdir(parents=True)
    outside.write_text("def fail():\n    raise ValueError('deep')\n")
    namespace: dict[str, object] = {}
    exec(compile(outside.read_text(), str(outside), "exec"), namespace)

    def product_frame() -> None:
        namespace["fail"]()  # type: ignore[operator]

    with pytest.raises(ValueError) as info:
        product_frame()
    # The test's own frame is not in the package either: no location at all.
    assert describe_exception(info.value) == "ValueError: deep"

    # Called from the package: the location is the package's innermost frame.
    with pytest.raises(ValueError) as info:
        thread_map(lambda _: namespace["fail"](), [0], 1)  # type: ignore[operator]
    text = describe_exception(info.value)
    assert "(in <listcomp>, threads.py:" in text, text  # edgerecon/threads.py
