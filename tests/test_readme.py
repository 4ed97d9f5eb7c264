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
    from vrs_jax.data.readers import load_scene

    code = _example()
    lines = [x for x in code.splitlines() if x.strip()]
    assert len(lines) <= 6
    queries = load_scene("7scenes", small_synthetic_scene).queries()
    code = code.replace('"maps/room"', repr(str(tiny_map)))
    code = code.replace('"query.png"', repr(str(queries.image_paths[0])))
    code = code.replace('"cpu-small"', '"test"')  # the tiny map's config
    ns = {"K": queries.K[0], "dist": queries.dist[0]}
    exec(compile(code, str(README), "exec"), ns)
    r = ns["result"]
    assert np.asarray(r.R).shape == (3, 3) and np.all(np.isfinite(np.asarray(r.t)))
    assert bool(r.success) != bool(r.fallback)
