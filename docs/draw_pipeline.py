"""Draw the pipeline figure of the README and the docs home page: ``docs/_static/pipeline.svg``.

Usage::

    python docs/draw_pipeline.py           # rewrite the figure
    python docs/draw_pipeline.py --check   # exit 1 if the committed figure differs

Plain SVG written by hand (no plotting library), so the figure is small, sharp at any size and
the same on every machine.  The hash pattern and the activity packet are drawn from fixed
numbers: they illustrate the shapes, they are not data.  It shows the default method,
kenyon+cann; the paper's FlyHash -> FlyNet front end fits in the same place.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent / "_static" / "pipeline.svg"
WIDTH, HEIGHT = 960, 190
BOX_W, BOX_H, TOP, GAP = 140, 140, 36, 28
PIC_Y = TOP + 100  # top of the small picture inside each box
INK, MUTED, ACCENT, FILL = "#1f2937", "#6b7280", "#b45309", "#f8fafc"

#: the default method, kenyon+cann (the paper's FlyHash -> FlyNet front end is another choice)
STAGES = [
    ("camera frame", ["any size, colour"]),
    ("gray 32 x 64", ["area-averaged,", "values in [0, 1]"]),
    ("optic lobe", ["fixed filters:", "local contrast,", "oriented edges"]),
    ("Kenyon cells", ["4096 cells, sparse", "inputs, 5% fire:", "512 bytes a place"]),
    ("CANN", ["probability over", "places and speeds,", "moved by the motion"]),
]
OUTPUT = ["place,", "confidence,", "localized or lost"]


def _text(x, y, s, size=13, color=INK, weight="normal", anchor="middle") -> str:
    return (
        f'<text x="{x:.1f}" y="{y:.1f}" font-size="{size}" fill="{color}" '
        f'font-weight="{weight}" text-anchor="{anchor}">{s}</text>'
    )


def _box(x, title, lines) -> list[str]:
    cx = x + BOX_W / 2
    out = [
        f'<rect x="{x}" y="{TOP}" width="{BOX_W}" height="{BOX_H}" rx="10" fill="{FILL}" '
        f'stroke="{INK}" stroke-width="1.5"/>',
        _text(cx, TOP + 22, title, size=15, weight="bold"),
    ]
    out += [_text(cx, TOP + 42 + 15 * i, s, size=12, color=MUTED) for i, s in enumerate(lines)]
    return out


def _arrow(x0, x1, y) -> str:
    return (
        f'<line x1="{x0}" y1="{y}" x2="{x1 - 6}" y2="{y}" stroke="{INK}" stroke-width="1.5"/>'
        f'<polygon points="{x1},{y} {x1 - 8},{y - 4} {x1 - 8},{y + 4}" fill="{INK}"/>'
    )


def _landscape(x) -> list[str]:
    """A colour picture: sky, sun, hills."""
    x0, w, h = x + 35, BOX_W - 70, 28
    return [
        f'<rect x="{x0}" y="{PIC_Y}" width="{w}" height="{h}" fill="#bfdbfe"/>',
        f'<circle cx="{x0 + w - 14}" cy="{PIC_Y + 8}" r="5" fill="#facc15"/>',
        f'<polygon points="{x0},{PIC_Y + h} {x0 + 22},{PIC_Y + 9} {x0 + 42},{PIC_Y + h}" '
        'fill="#15803d"/>',
        f'<polygon points="{x0 + 28},{PIC_Y + h} {x0 + 52},{PIC_Y + 14} {x0 + w},{PIC_Y + h}" '
        'fill="#166534"/>',
    ]


def _gray(x) -> list[str]:
    """An 8 x 4 block of gray pixels (fixed levels)."""
    levels = "9ab8765489bccb9745679aa987643568"
    size = 7
    x0 = x + (BOX_W - 8 * size) / 2
    return [
        f'<rect x="{x0 + (i % 8) * size}" y="{PIC_Y + (i // 8) * size}" width="{size}" '
        f'height="{size}" fill="#{c}{c}{c}{c}{c}{c}"/>'
        for i, c in enumerate(levels)
    ]


def _edges(x) -> list[str]:
    """Eight small oriented edges (0, 45, 90 and 135 degrees), as the lobe's filters see."""
    size, gap = 10, 6
    x0 = x + (BOX_W - 4 * size - 3 * gap) / 2
    out = []
    for i in range(8):
        angle = math.radians(45 * (i % 4))
        cx = x0 + (i % 4) * (size + gap) + size / 2
        cy = PIC_Y + 5 + (i // 4) * (size + 4)
        dx, dy = 0.5 * size * math.cos(angle), 0.5 * size * math.sin(angle)
        out.append(
            f'<line x1="{cx - dx:.1f}" y1="{cy - dy:.1f}" x2="{cx + dx:.1f}" y2="{cy + dy:.1f}" '
            f'stroke="{ACCENT if i in (1, 6) else MUTED}" stroke-width="2"/>'
        )
    return out


def _kenyon(x) -> list[str]:
    """32 of the 4096 cells in two rows: a fixed sparse pattern, two of them firing."""
    pattern = "00000010000000000000000000010000"
    size = 6
    x0 = x + (BOX_W - 16 * (size + 1)) / 2
    return [
        f'<rect x="{x0 + (i % 16) * (size + 1):.1f}" y="{PIC_Y + 4 + (i // 16) * (size + 2)}" '
        f'width="{size}" height="{size}" fill="{ACCENT if bit == "1" else "#d1d5db"}"/>'
        for i, bit in enumerate(pattern)
    ]


def _packet(x) -> list[str]:
    """A Gaussian bump of activity over a line of place units."""
    x0, w = x + 15, BOX_W - 30
    pts = [
        f"{x0 + i / 40 * w:.1f},{PIC_Y + 24 - 22 * math.exp(-(((i / 40 - 0.62) / 0.08) ** 2)):.1f}"
        for i in range(41)
    ]
    return [
        f'<line x1="{x0}" y1="{PIC_Y + 24.5}" x2="{x0 + w}" y2="{PIC_Y + 24.5}" stroke="{MUTED}"/>',
        f'<polyline points="{" ".join(pts)}" fill="none" stroke="{ACCENT}" stroke-width="2"/>',
    ]


def draw() -> str:
    """The SVG document."""
    xs = [10 + i * (BOX_W + GAP) for i in range(len(STAGES))]
    mid = TOP + BOX_H / 2
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" '
        f'viewBox="0 0 {WIDTH} {HEIGHT}" font-family="Helvetica, Arial, sans-serif">',
        f'<rect width="{WIDTH}" height="{HEIGHT}" fill="white"/>',
        _text(
            10,
            22,
            "flyvpr's default (kenyon+cann), one frame at a time",
            size=13,
            color=MUTED,
            anchor="start",
        ),
    ]
    pictures = [_landscape, _gray, _edges, _kenyon, _packet]
    for x, (title, lines), picture in zip(xs, STAGES, pictures, strict=True):
        parts += _box(x, title, lines)
        parts += picture(x)
    ends = [x + BOX_W for x in xs]
    for a, b in zip(ends, xs[1:] + [ends[-1] + GAP], strict=True):
        parts.append(_arrow(a + 3, b - 3, mid))
    out_x = ends[-1] + GAP + 4
    for i, s in enumerate(OUTPUT):
        size, weight = (14, "bold") if i < 2 else (12, "normal")
        parts.append(_text(out_x, mid - 14 + 18 * i, s, size=size, weight=weight, anchor="start"))
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the figure is stale")
    args = parser.parse_args(argv)
    svg = draw()
    if args.check:
        ok = OUT.is_file() and OUT.read_text() == svg
        print(f"{OUT.name}: {'up to date' if ok else 'stale (run python docs/draw_pipeline.py)'}")
        return 0 if ok else 1
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(svg)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
