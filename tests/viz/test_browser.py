"""The match view in a real browser: Debian's chromium, headless, offline.

The Makefile installs chromium (``apt-get install chromium``); when it is absent the tests skip
and say so. Nothing is installed at test time.
"""

from __future__ import annotations

import pytest

from graffmatch.viz.browser import find_chromium, render_html
from graffmatch.viz.match_view import write_match_view

CHROMIUM = find_chromium()
pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="chromium not installed (Debian: apt-get install chromium; the Makefile does it)",
)


def _load_png(path):
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))
    return img[..., :3].astype(float)  # RGB in [0, 1]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from tests.viz.conftest import make_scene

    sc = make_scene()
    d = tmp_path_factory.mktemp("browser")
    html = write_match_view(
        d / "view.html",
        sc.source,
        sc.target,
        sc.T_target_source,
        sc.associations,
        sc.source_points,
        sc.target_points,
        sc.inlier_mask,
        title="browser test",
    )
    return render_html(html, screenshot=d / "view.png")


def test_page_renders_a_webgl_scene_without_console_errors(rendered):
    assert rendered.rendered, "plotly did not draw the scene (no canvas / marker missing)"
    body = rendered.body_attributes
    assert "data-graffmatch-error" not in body, body
    assert rendered.errors == [], f"console errors: {rendered.errors}"
    # every trace of the figure made it into the page
    assert int(body["data-graffmatch-traces"]) >= 20


def test_screenshot_is_not_blank_and_shows_both_scans(rendered):
    img = _load_png(rendered.screenshot)
    assert img.shape[0] >= 550 and img.shape[1] >= 1000
    assert img.std() > 0.05  # not a blank page
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    # side by side (the initial state here), both scans are in view in their own colours
    orange = (r - b > 0.3) & (r > 0.6)  # target scan, landmarks
    blue = b - r > 0.3  # source scan, landmarks
    green = (g - r > 0.25) & (g - b > 0.25)  # inlier correspondences
    assert orange.sum() > 500, "target scan not visible"
    assert blue.sum() > 500, "source scan not visible"
    assert green.sum() > 200, "correspondences not visible"


def test_console_errors_are_detected(tmp_path):
    """Negative control: a page that throws must be reported, else the test above is vacuous."""
    page = tmp_path / "bad.html"
    page.write_text(
        "<html><body><script>console.error('graffmatch-boom');"
        "undefined_function_xyz();</script></body></html>"
    )
    res = render_html(page, budget_ms=500)
    assert not res.rendered
    joined = " ".join(res.errors)
    assert "graffmatch-boom" in joined and "undefined_function_xyz" in joined
