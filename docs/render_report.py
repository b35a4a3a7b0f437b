"""Render an experiment report in headless Chromium and check that it displays.

Checks that every ``<img>`` of the HTML decoded (``naturalWidth > 0`` after the
page's load event, read back with ``--dump-dom``) and that a full-page
screenshot is not blank (pixel spread and share of non-white pixels).

Usage::

    python docs/render_report.py DIR/report.html [--screenshot out.png]
                                       [--width 1280] [--height 4000] [--chromium PATH]

Exit status 0 when every check passes, 1 when one fails, 2 when no Chromium
is found.  Needs a Chromium or Chrome binary (Debian: ``apt-get install chromium``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

#: flags for a quiet, offline, sandbox-free (root in containers) headless browser
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
)

#: appended to a copy of the page: records images found / decoded on <html>
PROBE = """<script>
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.documentElement.setAttribute("data-images", imgs.length + "/" + ok);
});
</script>"""


def find_browser(explicit: str | None = None) -> str | None:
    if explicit:
        return explicit
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def _run(browser: str, args: list[str], timeout: float) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory() as profile:
        cmd = [browser, *FLAGS, f"--user-data-dir={profile}", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)


def check_images(browser: str, html_path: Path, timeout: float = 120) -> tuple[int, int, int]:
    """(images in the file, images in the DOM, images decoded) for ``html_path``."""
    text = html_path.read_text(encoding="utf-8")
    n_file = len(re.findall(r"<img\b", text))
    probe_text = text.replace("</body>", PROBE + "</body>", 1)
    with tempfile.TemporaryDirectory() as tmp:
        probe = Path(tmp) / "probe.html"
        probe.write_text(probe_text, encoding="utf-8")
        proc = _run(browser, ["--virtual-time-budget=15000", "--dump-dom", probe.as_uri()], timeout)
    match = re.search(r'data-images="(\d+)/(\d+)"', proc.stdout)
    if match is None:
        raise RuntimeError(
            f"the page reported no image count; browser exit {proc.returncode}, "
            f"stderr tail: {proc.stderr[-500:]}"
        )
    return n_file, int(match.group(1)), int(match.group(2))


def screenshot(
    browser: str, html_path: Path, out: Path, width: int, height: int, timeout: float = 120
) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    proc = _run(
        browser,
        [
            f"--screenshot={out}",
            f"--window-size={width},{height}",
            "--virtual-time-budget=15000",
            html_path.resolve().as_uri(),
        ],
        timeout,
    )
    if not out.is_file():
        raise RuntimeError(
            f"no screenshot written; browser exit {proc.returncode}, stderr tail: "
            f"{proc.stderr[-500:]}"
        )


def blank_stats(png: Path) -> tuple[float, float]:
    """(standard deviation of gray levels, share of pixels darker than near-white)."""
    gray = np.asarray(Image.open(png).convert("L"), dtype=np.float64)
    return float(gray.std()), float(np.mean(gray < 240))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("html", type=Path, help="report.html to render")
    parser.add_argument("--screenshot", type=Path, help="PNG to write (default: beside the HTML)")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=4000)
    parser.add_argument("--chromium", help="browser binary (default: first found on PATH)")
    args = parser.parse_args(argv)

    if not args.html.is_file():
        print(f"no such file: {args.html}", file=sys.stderr)
        return 1
    browser = find_browser(args.chromium)
    if browser is None:
        print(f"no browser found (tried {', '.join(BROWSERS)})", file=sys.stderr)
        return 2
    out = args.screenshot or args.html.with_name("report_screenshot.png")
    os.environ.setdefault("LANG", "C.UTF-8")

    n_file, n_dom, n_ok = check_images(browser, args.html)
    screenshot(browser, args.html, out, args.width, args.height)
    spread, inked = blank_stats(out)
    failures = []
    if n_dom != n_file:
        failures.append(f"the DOM holds {n_dom} images, the file {n_file}")
    if n_ok != n_dom:
        failures.append(f"only {n_ok} of {n_dom} images decoded")
    if spread < 5 or inked < 0.01:
        failures.append(f"screenshot looks blank (gray sd {spread:.1f}, {100 * inked:.2f}% ink)")
    print(
        f"{args.html}: {n_ok}/{n_dom} images decoded ({n_file} <img> in the file); "
        f"screenshot {out}: gray sd {spread:.1f}, {100 * inked:.1f}% non-white pixels"
    )
    for failure in failures:
        print(f"FAIL: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
