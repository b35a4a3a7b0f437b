"""A trace of a localization run that people can watch: an ``.mp4`` video or an ``.html`` page.

Each frame shows the query image, the matched place's thumbnail from the map, the filter's
activity over all places (the CANN's place units, normalised per frame, the matched place
marked) and the confidence over time, with a red mark where the filter relocated its packet;
the caption says ``LOST`` on frames where the filter is lost (its place is only a hint).
Everything is drawn with numpy (and Pillow for one line of text), so no plotting library is
needed.  The video is encoded with PyAV as it goes (H.264, or MPEG-4 Part 2 where libx264 is
missing), so memory does not grow with the run; the page keeps a small summary per frame (the
query thumbnail and the activity in :data:`HTML_BINS` bins) and is written at the end.
"""

from __future__ import annotations

import base64
import io
import json
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .._io import atomic_open
from .localizer import LOST

__all__ = ["VideoTrace", "HtmlTrace", "open_trace", "HTML_BINS"]

#: activity bins per frame kept by the HTML trace
HTML_BINS = 256
_W = 512  # canvas width: two images of 256 px side by side
_IMG_H = 128
_PLOT_H = 64
#: height of the tick above a relocated frame's confidence bar (it leaves the bar visible)
_RELOC_H = 6
_TEXT_H = 16
_H = _TEXT_H + _IMG_H + 2 * _PLOT_H
_BLUE = np.array([70, 130, 220], np.uint8)
_GREEN = np.array([60, 180, 90], np.uint8)
_RED = np.array([220, 50, 50], np.uint8)


def _upscale(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resize of a uint8 gray image to (h, w) by index arrays (no loop)."""
    rows = np.arange(h) * img.shape[0] // h
    cols = np.arange(w) * img.shape[1] // w
    return img[rows[:, None], cols[None, :]]


def _binned(row: np.ndarray, n_bins: int) -> np.ndarray:
    """Max of ``row`` over ``n_bins`` consecutive bins (each place in at least one bin)."""
    n = row.shape[0]
    starts = np.arange(n_bins) * n // n_bins
    if n < n_bins:
        return row[starts]
    return np.maximum.reduceat(row, starts)


def _normalised(values: np.ndarray) -> np.ndarray:
    lo, hi = float(np.min(values)), float(np.max(values))
    return (values - lo) / (hi - lo) if hi > lo else np.zeros_like(values, dtype=np.float64)


def _probabilities(the_map) -> bool:
    """Whether the map's method says its confidence as a probability in [0, 1]: a filter that
    reports a state (the CANN).  The trace draws it on that scale; a raw score (no filter, or
    one without a state) from the lowest to the highest seen."""
    return hasattr(getattr(getattr(the_map, "method", None), "filter", None), "state_")


def _bars(heights: np.ndarray, plot_h: int, colour) -> np.ndarray:
    """An RGB panel (plot_h, len(heights), 3) with a bar of ``heights`` (in [0, 1]) per column."""
    top = plot_h - np.rint(np.clip(heights, 0, 1) * (plot_h - 1)).astype(int) - 1
    mask = np.arange(plot_h)[:, None] >= top[None, :]
    panel = np.full((plot_h, heights.shape[0], 3), 250, np.uint8)
    panel[mask] = colour
    return panel


class VideoTrace:
    """Write a trace video frame by frame (use :func:`open_trace`)."""

    def __init__(self, fh, path: Path, the_map, fps: float = 10.0):
        from ..sources.base import require_extra

        av = require_extra("av")
        self.map = the_map
        self.container = av.open(fh, "w", format="matroska" if path.suffix == ".mkv" else "mp4")
        codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
        self.stream = self.container.add_stream(codec, rate=int(fps))
        self.stream.width, self.stream.height, self.stream.pix_fmt = _W, _H, "yuv420p"
        self._av = av
        self.history = np.zeros(_W)
        self.relocs = np.zeros(_W, bool)
        self.n = 0
        self.probabilities = _probabilities(the_map)

    def add(self, step) -> None:
        for i in range(len(step.places)):
            self.history = np.roll(self.history, -1)
            self.relocs = np.roll(self.relocs, -1)
            self.history[-1] = step.confidences[i]
            self.relocs[-1] = step.relocated[i]
            canvas = self._draw(step, i)
            frame = self._av.VideoFrame.from_ndarray(canvas, format="rgb24")
            self.container.mux(self.stream.encode(frame))
            self.n += 1

    def _draw(self, step, i) -> np.ndarray:
        m, place = self.map, int(step.places[i])
        canvas = np.full((_H, _W, 3), 255, np.uint8)
        query = np.rint(step.batch.images[i] * 255).astype(np.uint8)
        y = _TEXT_H
        canvas[y : y + _IMG_H, : _W // 2] = _upscale(query, _IMG_H, _W // 2)[..., None]
        if m.thumbnails is not None:
            ref = _upscale(m.thumbnails[place], _IMG_H, _W // 2)
            canvas[y : y + _IMG_H, _W // 2 :] = ref[..., None]
        y += _IMG_H
        act = _normalised(_binned(step.scores[i].astype(np.float64), _W))
        panel = _bars(act, _PLOT_H, _BLUE)
        panel[:, (2 * place + 1) * _W // (2 * m.n_places)] = _RED  # the place's centre
        canvas[y : y + _PLOT_H] = panel
        y += _PLOT_H
        seen = min(self.n + 1, _W)
        hist = np.zeros(_W)
        # a probability on its own scale (the same bar height for a frame all the video
        # long); a raw score from the lowest to the highest seen so far
        recent = self.history[-seen:]
        hist[-seen:] = recent if self.probabilities else _normalised(recent)
        panel = _bars(hist, _PLOT_H, _GREEN)
        panel[:_RELOC_H, self.relocs] = _RED  # a tick above a relocation's bar
        canvas[y : y + _PLOT_H] = panel
        img = Image.fromarray(canvas)
        b = step.batch
        t = b.timestamps[i]
        text = (
            f"frame {int(b.indices[i])}" + (f"  t={t:.2f}s" if np.isfinite(t) else "")
            + f"  place {place}  conf {float(step.confidences[i]):.3g}"
            + ("  LOST" if step.states[i] == LOST else "")
            + ("  RELOCATED" if step.relocated[i] else "")
        )  # fmt: skip
        ImageDraw.Draw(img).text((4, 2), text, fill=(0, 0, 0))
        return np.asarray(img)

    def close(self) -> None:
        self.container.mux(self.stream.encode(None))
        self.container.close()


class HtmlTrace:
    """Collect a per-frame summary and write a self-contained page (use :func:`open_trace`)."""

    def __init__(self, fh, path: Path, the_map):
        self.fh, self.map = fh, the_map
        self.queries: list[np.ndarray] = []
        self.activity: list[np.ndarray] = []
        self.rows: list[list] = []  # one JSON row per frame

    def add(self, step) -> None:
        b = step.batch
        self.queries.append(np.rint(b.images * 255).astype(np.uint8))
        for i in range(len(step.places)):
            act = _normalised(_binned(step.scores[i].astype(np.float64), HTML_BINS))
            self.activity.append(np.rint(act * 255).astype(np.uint8))
            t = float(b.timestamps[i])
            self.rows.append(
                [int(b.indices[i]), t if np.isfinite(t) else None, int(step.places[i]),
                 float(step.confidences[i]), bool(step.relocated[i]), str(step.states[i])]
            )  # fmt: skip

    def close(self) -> None:
        m = self.map
        queries = np.concatenate(self.queries) if self.queries else np.zeros((0, 1, 1), np.uint8)
        h, w = queries.shape[1:] if len(queries) else m.size
        thumbs = m.thumbnails if m.thumbnails is not None else np.zeros((m.n_places, h, w))
        data = {
            "probabilities": _probabilities(m),
            "h": int(h),
            "w": int(w),
            "n_places": m.n_places,
            "bins": HTML_BINS,
            "rows": self.rows,
            "activity": base64.b64encode(np.asarray(self.activity, np.uint8).tobytes()).decode(),
            "queries": _png_sprite(queries),
            "places": _png_sprite(np.asarray(thumbs, np.uint8)),
        }
        self.fh.write(_PAGE.replace("__DATA__", json.dumps(data)))


def _png_sprite(stack: np.ndarray) -> str:
    """A stack (n, h, w) as one tall gray PNG, base64 (a data URL)."""
    n, h, w = stack.shape
    sheet = stack.reshape(n * h, w) if n else np.zeros((h, w), np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(sheet)).save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


@contextmanager
def open_trace(path, the_map):
    """A trace writer for ``path`` (``.mp4``/``.mkv`` video or ``.html``), written atomically.

    Use as ``with open_trace(path, map) as t: t.add(step)`` for each
    :class:`flyvpr.localization.tracking.Step`.
    """
    path = Path(path)
    html = path.suffix.lower() in (".html", ".htm")
    with atomic_open(path, "w" if html else "w+b", **({"encoding": "utf-8"} if html else {})) as fh:
        tracer = HtmlTrace(fh, path, the_map) if html else VideoTrace(fh, path, the_map)
        yield tracer
        tracer.close()


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>flyvpr trace</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{font:14px sans-serif;margin:1em}
canvas{border:1px solid #ccc;display:block;width:512px;max-width:100%}
#slider{width:512px;max-width:calc(100% - 5em)}#info{margin:.4em 0}</style></head><body>
<h1>flyvpr localization trace</h1>
<div><button id="play">play</button> <input id="slider" type="range" min="0" value="0"></div>
<div id="info"></div>
<p>query frame | matched place; activity over places (red: matched place);
confidence over time, <span id="scale"></span> (red tick: relocation, black: this frame)</p>
<canvas id="c" width="512" height="272"></canvas>
<script>
const D = __DATA__;
const act = Uint8Array.from(atob(D.activity), c => c.charCodeAt(0));
const q = new Image(); q.src = D.queries; const p = new Image(); p.src = D.places;
const c = document.getElementById("c"), g = c.getContext("2d");
const s = document.getElementById("slider"), info = document.getElementById("info");
const n = D.rows.length; s.max = Math.max(0, n - 1);
const confs = D.rows.map(r => r[3]);
// a probability on its own scale, 0 to 1; a raw score from the run's lowest to its highest
const lo = D.probabilities ? 0 : Math.min(...confs), hi = D.probabilities ? 1 : Math.max(...confs);
document.getElementById("scale").textContent = D.probabilities ? "bar height 0 to 1" :
  "bar height from the run's lowest score (" + lo.toPrecision(3) + ") to its highest (" +
  hi.toPrecision(3) + ")";
g.imageSmoothingEnabled = false;
function draw(i) {
  const r = D.rows[i]; if (!r) return;
  g.fillStyle = "#fff"; g.fillRect(0, 0, 512, 272);
  g.drawImage(q, 0, i * D.h, D.w, D.h, 0, 0, 256, 128);
  g.drawImage(p, 0, r[2] * D.h, D.w, D.h, 256, 0, 256, 128);
  g.fillStyle = "#4682dc";
  for (let b = 0; b < D.bins; b++) {
    const v = act[i * D.bins + b] / 255 * 63;
    g.fillRect(b * 512 / D.bins, 192 - v, 512 / D.bins, v);
  }
  g.fillStyle = "#dc3232"; g.fillRect((r[2] + 0.5) * 512 / D.n_places - 1, 128, 2, 64);
  const wide = Math.max(1, 512 / n);
  for (let k = 0; k < n; k++) {
    const x = k * 512 / n;
    const v = hi > lo ? Math.min(Math.max((confs[k] - lo) / (hi - lo), 0), 1) * 63 : 0;
    g.fillStyle = "#3cb45a"; g.fillRect(x, 256 - v, wide, v);
    if (D.rows[k][4]) { g.fillStyle = "#dc3232"; g.fillRect(x, 192, wide, 6); }
  }
  g.fillStyle = "#000"; g.fillRect(Math.max(1, (i + 0.5) * 512 / n - 0.5), 192, 1, 64);
  info.textContent = "frame " + r[0] + (r[1] === null ? "" : "  t=" + r[1].toFixed(2) + " s") +
    "  place " + r[2] + "  confidence " + r[3].toPrecision(3) + (r[5] === "lost" ? "  LOST" : "") +
    (r[4] ? "  RELOCATED" : "");
}
let timer = null;
document.getElementById("play").onclick = () => {
  if (timer) { clearInterval(timer); timer = null; return; }
  timer = setInterval(() => { s.value = (+s.value + 1) % n; draw(+s.value); }, 100);
};
s.oninput = () => draw(+s.value);
q.onload = p.onload = () => draw(+s.value);
</script></body></html>
"""
