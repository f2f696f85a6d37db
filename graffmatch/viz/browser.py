"""Render an HTML view in a real headless browser (Debian's chromium), offline.

Used by the browser test and to make the screenshots of the docs and reports: the page is opened
with every network feature off, the DOM after rendering is dumped (the view marks ``<body>`` with
``data-graffmatch-rendered``) and the browser's console messages are collected from its log.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from graffmatch.errors import GraffMatchError

#: Candidate executables, Debian's first.
CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "chromium", "chromium-browser", "google-chrome")

#: Flags that keep the browser offline and quiet (no updates, sync, QUIC, first-run UI).
OFFLINE_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-default-apps",
    "--metrics-recording-only",
    "--hide-scrollbars",
    "--proxy-server=127.0.0.1:9",  # any request that escapes file:// fails fast
    "--enable-logging=stderr",
    "--v=0",
)

_CONSOLE = re.compile(r":CONSOLE[:(]?\d*\)?\]\s*\"(?P<msg>.*)\", source: (?P<src>\S*)")

#: Console messages of the software GL path that are not page errors.
BENIGN_CONSOLE = (
    "GL Driver Message",
    "Automatic fallback to software WebGL",
    "willReadFrequently",
    "WebGL: too many errors",
)


class BrowserError(GraffMatchError):
    """The browser is missing or failed to render the page."""


def find_chromium() -> str | None:
    for cand in CHROMIUM_CANDIDATES:
        path = shutil.which(cand)
        if path:
            return path
    return None


@dataclass
class RenderResult:
    dom: str
    console: list[str] = field(default_factory=list)
    screenshot: Path | None = None

    @property
    def errors(self) -> list[str]:
        """Console messages that are not known-benign driver chatter."""
        return [m for m in self.console if not any(b in m for b in BENIGN_CONSOLE)]

    @property
    def body_attributes(self) -> dict[str, str]:
        """Attributes of the rendered ``<body>`` (where the view leaves its marks)."""
        m = re.search(r"<body([^>]*)>", self.dom, flags=re.IGNORECASE)
        return dict(re.findall(r'([\w-]+)="([^"]*)"', m.group(1))) if m else {}

    @property
    def rendered(self) -> bool:
        return self.body_attributes.get("data-graffmatch-rendered") == "1"


def _run(cmd: list[str], timeout: float) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired as exc:
        raise BrowserError(f"chromium did not finish within {timeout:.0f} s") from exc


def render_html(
    html: str | Path,
    screenshot: str | Path | None = None,
    width: int = 1280,
    height: int = 800,
    budget_ms: int = 8000,
    timeout: float = 90.0,
    chromium: str | None = None,
) -> RenderResult:
    """Open ``html`` headless and offline; return the rendered DOM, console messages and PNG.

    The PNG is the page as laid out: chromium's new headless mode uses a viewport about 140 px
    shorter than ``height``, and the blank rows below it are cropped.
    """
    exe = chromium or find_chromium()
    if exe is None:
        raise BrowserError("chromium not found (Debian: apt-get install chromium)")
    html = Path(html).resolve()
    if not html.is_file():
        raise BrowserError(f"{html}: page not found")
    url = html.as_uri()
    with tempfile.TemporaryDirectory(prefix="graffmatch-chromium-") as profile:
        base = [
            exe,
            *OFFLINE_FLAGS,
            f"--user-data-dir={profile}",
            f"--window-size={width},{height}",
            f"--virtual-time-budget={budget_ms}",
        ]
        shot = None
        extra = []
        if screenshot is not None:
            # One browser run does both: the DOM on stdout and the PNG on disk.
            shot = Path(screenshot).resolve()
            shot.parent.mkdir(parents=True, exist_ok=True)
            shot.unlink(missing_ok=True)
            extra = [f"--screenshot={shot}"]
        proc = _run([*base, "--dump-dom", *extra, url], timeout)
        if proc.returncode != 0 or "<html" not in proc.stdout.lower():
            tail = " | ".join(proc.stderr.strip().splitlines()[-3:])
            raise BrowserError(f"chromium failed on {html} (exit {proc.returncode}): {tail}")
        console = [m.group("msg") for m in _CONSOLE.finditer(proc.stderr)]
        if shot is not None and not shot.is_file():
            raise BrowserError(f"chromium wrote no screenshot for {html}")
    result = RenderResult(proc.stdout, sorted(set(console)), shot)
    if shot is not None:
        _crop_to_viewport(shot, result.body_attributes.get("data-graffmatch-viewport"))
    return result


def _crop_to_viewport(png: Path, viewport: str | None) -> None:
    """New headless chromium lays the page out in a viewport shorter than the screenshot
    (room for an invisible toolbar); the page measured its size at load, so the rows below the
    viewport are blank. Crop them away so that the PNG is the page as laid out."""
    if not viewport or "x" not in viewport:
        return
    import matplotlib.image as mpimg

    try:
        w, h = (int(v) for v in viewport.split("x"))
    except ValueError:
        return
    img = mpimg.imread(str(png))
    if 0 < h < img.shape[0] and 0 < w <= img.shape[1]:
        mpimg.imsave(str(png), img[:h, :w])
