"""The README's Python example of an adaptation run runs as printed (on fewer frames)."""

import contextlib
import io
import math
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_block(containing: str) -> str:
  blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
  found = [b for b in blocks if containing in b]
  assert len(found) == 1, f"README: {len(found)} python blocks contain {containing!r}"
  return found[0]


def test_adaptation_example_runs():
  code = _python_block("make_method_runner")
  assert "num_frames=64" in code and "AdaptConfig()" in code
  # 3 frames in one chunk of 3 (with the default 32, 29 padded steps would run too); the
  # program is the example's own compile (no other test compiles the shipped model's step)
  code = code.replace("num_frames=64", "num_frames=3").replace("AdaptConfig()",
                                                               "AdaptConfig(chunk_size=3)")
  out = io.StringIO()
  with contextlib.redirect_stdout(out):
    exec(compile(code, str(README), "exec"), {})
  lines = [line.split(" ", 1) for line in out.getvalue().splitlines()]
  assert [step for step, _ in lines] == ["3"]
  shape, loss = lines[0][1].rsplit(" ", 1)
  assert shape == "(3, 96, 320)" and math.isfinite(float(loss))
