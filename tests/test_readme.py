"""The README's Python example runs as written (paths and camera substituted) on the tiny map."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def _example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) == 1, "the README has one Python example"
    return blocks[0]


def test_readme_example_is_short_and_runs(tiny_map, small_synthetic_scene):
    """As printed, with the demo's two folders replaced by the test session's scene and map
    (a small room and the `test` config, which the block reads from the map)."""
    code = _example()
    lines = [x for x in code.splitlines() if x.strip()]
    assert len(lines) <= 8
    for demo_path, here in (('"outputs/demo/map"', tiny_map),
                            ('"outputs/demo/scene"', small_synthetic_scene)):
        assert demo_path in code
        code = code.replace(demo_path, repr(str(here)))
    ns: dict = {}
    exec(compile(code, str(README), "exec"), ns)
    r = ns["result"]
    assert np.asarray(r.R).shape == (3, 3) and np.all(np.isfinite(np.asarray(r.t)))
    assert bool(r.success) != bool(r.fallback)

