"""Draw the scaling curve of the large-maps guide from the committed benchmark run:
``benchmarks/scale.json`` -> ``docs/_static/scale.png``.

Usage::

    python docs/draw_scale.py [--json benchmarks/scale.json] [--out docs/_static/scale.png]

Needs matplotlib (``pip install flyvpr[plot]``).  Three panels against the map's places (log
scale), one line per relocation index: frames per second on the localized stream (dotted: the
frames whose code did not go to the index), peak resident memory of the localizing process, and
the share of kidnaps relocated within 30 frames; each with its target as a dashed
line.  The figure shows the JSON's numbers and nothing else.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
JSON = HERE.parent / "benchmarks" / "scale.json"
OUT = HERE / "_static" / "scale.png"

#: (row key, panel title, target, top of the axis or None)
PANELS = [
    ("frames_per_s", "frames/s on the localized stream", 1000.0, None),
    ("peak_rss_mb", "peak resident memory (MB)", 2048.0, 2600.0),
    ("kidnap_relocated_share", "kidnaps relocated within 30 frames", 0.9, 1.02),
]
LABELS = {"mih": "multi-index hashing (radius 1)", "exhaustive": "exact scan"}


def draw(rows: list[dict], out: Path) -> None:
    """Write the figure of ``rows`` (the JSON's list) to ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    indexes = sorted({r.get("index", "mih") for r in rows}, key=list(LABELS).index)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(12, 3.6), constrained_layout=True)
    for ax, (key, label, target, top) in zip(axes, PANELS, strict=True):
        for name, marker in zip(indexes, "os", strict=False):
            sel = sorted(
                (r for r in rows if r.get("index", "mih") == name), key=lambda r: r["places"]
            )
            (line,) = ax.plot(
                [r["places"] for r in sel],
                [r[key] for r in sel],
                marker=marker,
                label=LABELS.get(name, name),
            )
            if key == "frames_per_s":
                # the frames the window alone answered: the cost that does not grow with the map
                ax.plot(
                    [r["places"] for r in sel],
                    [r["tracked_frames_per_s"] for r in sel],
                    marker=marker,
                    linestyle=":",
                    color=line.get_color(),
                    label=f"{LABELS.get(name, name)}: frames not searched",
                )
        ax.axhline(target, color="0.4", linestyle="--", linewidth=1, label="target")
        ax.set_xscale("log")
        ax.set_ylim(0, top)
        ax.set_xlabel("places in the map")
        ax.set_title(label, fontsize=11)
        ax.grid(True, which="major", alpha=0.3)
    # one legend for all panels, where the memory panel has room
    axes[1].legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="center left")
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, default=JSON)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    try:
        rows = json.loads(args.json.read_text())
    except FileNotFoundError:
        print(f"no benchmark run at {args.json} (python benchmarks/scale.py ...)", file=sys.stderr)
        return 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    draw(rows, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
