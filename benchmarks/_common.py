"""What the benchmark scripts share: where the data is, peak memory, the machine.

Import it as ``from benchmarks._common import ...`` (a script run as ``python
benchmarks/X.py`` first puts the repository root on ``sys.path``).
"""

from __future__ import annotations

import os
import platform
import resource
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_DATA", "peak_rss_mb", "machine"]

#: the shared data folder beside the checkout (``../shared/data``)
DEFAULT_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB.

    ``VmHWM`` of /proc/self/status belongs to the current address space: unlike getrusage's
    ``ru_maxrss``, it does not carry the parent's peak over into a child started by fork +
    exec.  getrusage where /proc is absent.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict:
    """The platform, architecture, processor and CPU count, for a benchmark's JSON."""
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
    }


#: places of the long map of the speed benchmarks (the summer frames repeated)
LINE_PLACES = 35_768


def make_line_map(summer: np.ndarray, n_places: int, rng) -> np.ndarray:
    """Repeat the real frames with per-copy perturbations up to ``n_places`` frames."""
    reps = -(-n_places // len(summer))
    out = np.empty((n_places, *summer.shape[1:]), dtype=np.float32)
    for r in range(reps):
        lo = r * len(summer)
        hi = min(n_places, lo + len(summer))
        block = summer[: hi - lo]
        if r:
            gain = rng.uniform(0.9, 1.1)
            offset = rng.uniform(-0.03, 0.03)
            dy, dx = rng.integers(-1, 2, size=2)
            block = np.roll(block, (dy, dx), axis=(1, 2)) * gain + offset
            block = block + rng.normal(0.0, 0.01, block.shape).astype(np.float32)
        out[lo:hi] = np.clip(block, 0.0, 1.0)
    return out


def machine_sentence(data: dict) -> str:
    """The "Machine: ..." line of a results page from its JSON's ``machine`` (empty if none;
    fields the platform left empty, such as ``processor`` on some Linux, left out)."""
    m = {k: v for k, v in (data.get("machine") or {}).items() if v not in ("", None)}
    return f"Machine: {', '.join(f'{k} {v}' for k, v in m.items())}." if m else ""


def run_page_benchmark(doc: str, run, render_markdown, argv=None) -> int:
    """The command line of a benchmark that owns a results page: ``--data``, ``--json``,
    ``--quiet``; checks both paths before the run (a missing data folder, a JSON path that is a
    folder or in none), prints the page, writes the JSON atomically.  Exit status 1 with one
    line on stderr for a bad path."""
    import argparse
    import sys

    from flyvpr._io import write_json_atomic

    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    ap.add_argument("--json", type=Path, help="write the figures as JSON")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    args = ap.parse_args(argv)
    folder = args.data / "nordland_64x32"
    if not folder.is_dir():
        print(f"data folder not found: {folder} (--data names the folder that holds it)",
              file=sys.stderr)  # fmt: skip
        return 1
    if args.json is not None and (args.json.is_dir() or not args.json.parent.is_dir()):
        print(f"--json {args.json}: expected a file path in an existing folder", file=sys.stderr)
        return 1
    result = run(args.data, progress=not args.quiet)
    print(render_markdown(result))
    if args.json is not None:
        write_json_atomic(args.json, result)
    return 0
