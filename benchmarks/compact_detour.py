"""A compact map with a stretch of the road left out: the map's breaks against one route.

Usage::

    python benchmarks/compact_detour.py --json benchmarks/compact-detour.json [--data DIR]

Protocol: ``nordland_64x32`` summer frames build a compact map (``flyvpr map --compact``:
256-bit codes, encoder seed ``s``) of a window without the middle stretch of the accuracy
benchmark's detours (``DETOURS``: the dev window 0-999 without 400-699, the held-out window
2000-2399 without 2160-2279), with positions 10 m apart per frame number, so that they jump
where the stretch is left out.  The map's frames are copied to a temporary folder (removed
after the run).  The winter frames of the whole window are the query, in order, through
``compact_localizer`` with the map's breaks (its default) and with ``breaks=()`` (one route:
``flyvpr localize --no-breaks``).  Per window, seed (0-2) and reading:

* the share of the off-map frames (those of the left-out stretch) ``localized``;
* frames from the first frame on the map again until the answer is ``localized`` and right
  (within ``TOLERANCE`` frames), as the accuracy benchmark counts a rejoin;
* the AUC (``flyvpr.metrics.evaluate_answers``) over every frame, the off-map ones having no
  right answer (the accuracy benchmark's detours give the off-map frames within the tolerance
  of a kept place a match there: its AUCs of the same answers are 0.002-0.013 lower).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks._common import machine, machine_sentence, run_page_benchmark  # noqa: E402
from flyvpr.images import load_images  # noqa: E402
from flyvpr.large.recording import build_compact_map, compact_localizer, open_compact_map  # noqa: E402
from flyvpr.metrics import evaluate_answers  # noqa: E402

#: window -> (first frame, frames, first left out, first kept after it), frame numbers of the
#: window's own count (0 = its first frame)
DETOURS = {
    "dev (0-999)": (0, 1000, 400, 700),
    "held out (2000-2399)": (2000, 400, 160, 280),
}
SEEDS = (0, 1, 2)
TOLERANCE = 2
#: metres between the places of consecutive frame numbers
SPACING = 10.0
#: the two readings of the same map
READINGS = {"breaks": None, "one route": ()}


def kept(n: int, gap_lo: int, gap_hi: int) -> np.ndarray:
    """Frame numbers (of the window) the map keeps: all but ``gap_lo .. gap_hi - 1``."""
    return np.r_[0:gap_lo, gap_hi:n]


def positions_csv(keep: np.ndarray) -> str:
    """The map's positions file: its ``j``-th image at ``SPACING`` m per frame number."""
    return "frame,x,y\n" + "".join(f"{j},{SPACING * i},0\n" for j, i in enumerate(keep))


def score(places, states, confidences, truth, on_map: np.ndarray, back: int) -> dict:
    """One run's figures (see the module's text): ``places`` and ``truth`` as frame numbers
    of the window, ``on_map`` per query frame, ``back`` the first frame on the map again."""
    places, truth = np.asarray(places), np.asarray(truth)
    localized = np.asarray(states) == "localized"
    right = (np.abs(places - truth) <= TOLERANCE) & on_map
    after = np.arange(back, len(truth))
    hit = after[localized[after] & right[after]]
    return {
        "offmap_localized_share": float(localized[~on_map].mean()),
        "rejoin_frames": int(hit[0] - back) if hit.size else None,
        "auc": evaluate_answers(np.asarray(confidences), right, on_map)["auc"],
    }


def run(data: Path, progress: bool = True) -> dict:
    folder = data / "nordland_64x32"
    summer = sorted((folder / "summer").glob("*.png"))
    winter = sorted((folder / "winter").glob("*.png"))
    rows = []
    with tempfile.TemporaryDirectory(prefix="flyvpr-compact-detour-") as tmp:
        for window, (first, n, gap_lo, gap_hi) in DETOURS.items():
            keep = kept(n, gap_lo, gap_hi)
            maps = Path(tmp) / f"w{first}"
            images = maps / "summer"
            images.mkdir(parents=True)
            for i in keep:
                shutil.copy(summer[first + i], images / summer[first + i].name)
            xy = maps / "xy.csv"
            xy.write_text(positions_csv(keep))
            query = load_images(winter[first : first + n], progress=False)
            truth = np.arange(n)
            on_map = np.isin(truth, keep)
            for seed in SEEDS:
                if progress:
                    print(f"  {window}, seed {seed}", file=sys.stderr, flush=True)
                path = maps / f"s{seed}.fvmap"
                build_compact_map(images, path, positions=xy, random_state=seed)
                cmap = open_compact_map(path)
                for reading, breaks in READINGS.items():
                    loc = compact_localizer(cmap, breaks=breaks)
                    fixes = loc.update_batch(query)
                    row = score(
                        keep[fixes.places], fixes.states, fixes.confidences, truth, on_map, gap_hi
                    )
                    row.update(window=window, seed=seed, reading=reading, breaks=list(cmap.breaks))
                    rows.append(row)
    return {
        "benchmark": "compact-detour",
        "protocol": {
            "data": "nordland_64x32 summer (map) -> winter (query)",
            "detours": {k: list(v) for k, v in DETOURS.items()},
            "map": f"flyvpr map --compact (256 bits), positions {SPACING:g} m per frame number",
            "seeds": list(SEEDS),
            "tolerance": TOLERANCE,
            "readings": {"breaks": "the map's (compact_localizer's default)", "one route": "()"},
        },
        "machine": machine(),
        "rows": rows,
    }


def render_table(data: dict) -> str:
    """Per window and reading: the figures as seed 0 / 1 / 2."""
    rows = data["rows"]
    seeds = sorted({r["seed"] for r in rows})

    def cells(mine, key, fmt) -> str:
        return " / ".join("never" if mine[s][key] is None else fmt(mine[s][key]) for s in seeds)

    lines = [
        f"| window | reading | off-map frames `localized` | frames to rejoin | "
        f"AUC, tolerance {data['protocol']['tolerance']} |",
        "|---|---|---|---|---|",
    ]
    for window, (first, _, lo, hi) in data["protocol"]["detours"].items():
        for reading in data["protocol"]["readings"]:
            mine = {r["seed"]: r for r in rows if (r["window"], r["reading"]) == (window, reading)}
            if not mine:
                continue
            lines.append(
                f"| {window}, without {first + lo}-{first + hi - 1} | {reading} | "
                f"{cells(mine, 'offmap_localized_share', lambda v: f'{100 * v:.1f}%')} | "
                f"{cells(mine, 'rejoin_frames', str)} | "
                f"{cells(mine, 'auc', lambda v: f'{v:.3f}')} |"
            )
    return "\n".join(lines)


def render_markdown(data: dict) -> str:
    p = data["protocol"]
    lines = [
        "## Protocol",
        "",
        f"{p['data']}; {p['map']}; seeds {', '.join(map(str, p['seeds']))} (each cell: seed "
        f"{' / '.join(map(str, p['seeds']))}); tolerance {p['tolerance']}.",
        "",
        "## A compact map with a stretch left out",
        "",
        render_table(data),
        "",
    ]
    if machine_sentence(data):
        lines.append(machine_sentence(data))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    return run_page_benchmark(__doc__, run, render_markdown, argv)


if __name__ == "__main__":
    raise SystemExit(main())
