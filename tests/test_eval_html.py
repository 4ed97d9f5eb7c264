"""The run report (vrs_jax.eval.html, `localize --report`): its pictures, and the page in a
real headless browser (Chromium from the system packages; skipped where none is installed)."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest

from vrs_jax.cli import localize as cli
from vrs_jax.eval import html


def _decode(uri: str) -> np.ndarray:
    assert uri.startswith("data:image/png;base64,")
    buf = np.frombuffer(base64.b64decode(uri.split(",", 1)[1]), np.uint8)
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def test_png_uri_round_trips_rgb_and_float_grey():
    rgb = np.zeros((5, 7, 3), np.uint8)
    rgb[1, 2] = (255, 0, 0)  # red stays red: the RGB -> BGR order for OpenCV
    np.testing.assert_array_equal(_decode(html.png_uri(rgb)), rgb)
    grey = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    got = _decode(html.png_uri(grey))[..., 0]
    np.testing.assert_array_equal(got, np.round(grey * 255).astype(np.uint8))


def test_thumbnail_scale_and_points_land_on_their_pixels():
    img, s = html.to_rgb8(np.zeros((400, 960), np.float32), longest=480)
    assert img.shape == (200, 480, 3) and s == pytest.approx(0.5)
    # a keypoint at (100.5, 60.5), COLMAP convention: pixel centre (100, 60) -> (50, 30)
    html.draw_points(img, np.array([[100.5, 60.5]]), html.GREEN, s, radius=1)
    assert tuple(img[30, 50]) == html.GREEN and not img[30, 60].any()


def test_patch_table_places_each_patch_and_leaves_missing_grey():
    a, b = np.zeros((4, 4)), np.ones((4, 4))
    t = html.patch_table([[a, b, None], [b, a, a]], size=8)  # two pairs: two columns
    assert t.shape == (36, 24)
    assert t[2:10, 2:10].max() == 0 and t[14:22, 2:10].min() == 1
    np.testing.assert_array_equal(t[26:34, 2:10], 0.5)
    assert t[2:10, 14:22].min() == 1 and t[26:34, 14:22].max() == 0


def _chromium() -> str | None:
    for name in ("chromium-headless-shell", "chromium", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


CHECK_PAGE = """<!DOCTYPE html><html><body><div id="out">pending</div>
<iframe id="f" src="report.html" width="1200" height="800"></iframe>
<script>
document.getElementById('f').onload = function () {
  const imgs = Array.from(this.contentDocument.images);
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  document.getElementById('out').textContent = 'images=' + imgs.length + ' broken=' + broken;
};
</script></body></html>
"""


def browser_image_check(folder) -> tuple[int, int]:
    """(images on folder/report.html, images that failed to load) as headless Chromium sees
    them: a page beside the report loads it in a frame and counts."""
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium installed (Debian: apt-get install chromium-headless-shell)")
    (folder / "check.html").write_text(CHECK_PAGE)
    out = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu",
                          "--allow-file-access-from-files", "--virtual-time-budget=20000",
                          "--dump-dom", (folder / "check.html").as_uri()],
                         capture_output=True, text=True, timeout=120)
    m = re.search(r"images=(\d+) broken=(\d+)", out.stdout)
    assert m, (out.stdout[-2000:], out.stderr[-2000:])
    return int(m.group(1)), int(m.group(2))


def test_localize_report_opens_in_chromium_with_every_image(tiny_map, tmp_path):
    out = tmp_path / "run"
    assert cli.main(["--map", str(tiny_map), "--out", str(out), "--config", "test",
                     "--mode", "render", "--no-timing", "--quiet", "--report"]) == 0
    page = (out / "report.html").read_text()
    n_queries = page.count("<section id=")
    assert n_queries == 8 and "vrs-jax localization report" in page
    assert "t error (cm)" in page and "rendered patch" in page
    # the verdict column and each section show the pose confidence's verdict
    summary = json.loads((out / "summary.json").read_text())
    shown = summary["n_localized"] + summary["n_uncertain"]
    assert shown >= 6 and page.count("(confidence ") == 2 * shown
    assert page.count("localized (confidence ") == 2 * summary["n_localized"]
    # per query: the query image, its best reference, its patch pairs
    n_img, broken = browser_image_check(out)
    assert n_img == page.count("<img ") >= 2 * n_queries and broken == 0


def test_a_broken_image_is_seen_by_the_check(tmp_path):
    good = html.png_uri(np.zeros((2, 2), np.uint8))
    (tmp_path / "report.html").write_text(
        f'<html><body><img src="data:image/png;base64,AAAA"><img src="{good}"></body></html>')
    assert browser_image_check(tmp_path) == (2, 1)
