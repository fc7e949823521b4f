"""The README's Python example runs as written (on the tiny synthetic dataset)."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_api_example(tiny_dataset, tmp_path, capsys):
    text = README.read_text()
    block = text.split("### Python API", 1)[1]
    code = re.search(r"```python\n(.*?)```", block, re.S).group(1)
    code = (
        code.replace('"data/session1"', repr(str(tiny_dataset)))
        .replace("frames.read(100)", "frames.read(3)")
        .replace('"t100.ply"', repr(str(tmp_path / "t3.ply")))
    )
    exec(compile(code, "README.md", "exec"), {})
    assert (tmp_path / "t3.ply").stat().st_size > 1000
    out = capsys.readouterr().out
    assert "dense.depth" in out
