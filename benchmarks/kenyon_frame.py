"""Per-frame cost of the ``kenyon`` front end's single-frame path on a 35,768-place map.

Map: the 2400 ``nordland_64x32`` summer frames repeated to 35,768 places, ``random_state=0``.
Queries: winter frames 0-199, one at a time.  Each figure is the best of ``--repeat`` passes
over the 200 frames: ``encode`` of one image, ``score_codes`` of one code, and
``Localizer.update`` of ``kenyon+cann``; then ``encode`` of winter frames 0-999 as one batch.

    OMP_NUM_THREADS=1 python benchmarks/kenyon_frame.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from flyvpr.frontends.kenyon import KenyonEncoder
from flyvpr.images import list_images, load_images
from flyvpr.localization import Localizer
from flyvpr.methods import FILTERS, Method

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))
from benchmarks._common import DEFAULT_DATA, LINE_PLACES, make_line_map  # noqa: E402

N_PLACES = LINE_PLACES


def best_per_frame_ms(step, n: int, repeat: int) -> float:
    """Smallest mean time of ``step(i)`` over ``i < n``, across ``repeat`` passes, in ms."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for i in range(n):
            step(i)
        best = min(best, (time.perf_counter() - t0) / n)
    return 1e3 * best


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--repeat", type=int, default=5, help="passes per figure (best)")
    args = p.parse_args(argv)
    root = args.data / "nordland_64x32"
    if not root.is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 1
    summer = load_images(list_images(root / "summer"), progress=False)
    winter = load_images(list_images(root / "winter")[:1000], progress=False)
    line = make_line_map(summer, N_PLACES, np.random.default_rng(0))  # as speed.py's
    front = KenyonEncoder(random_state=0)
    loc = Localizer(Method("kenyon+cann", front, FILTERS["cann"]())).fit(line)
    frames = [winter[i : i + 1] for i in range(200)]
    codes = [front.encode(f) for f in frames]  # also compiles the kernels
    front.score_codes(codes[0])
    loc.update(winter[0])
    loc.reset()
    rep = args.repeat
    encode = best_per_frame_ms(lambda i: front.encode(frames[i]), 200, rep)
    score = best_per_frame_ms(lambda i: front.score_codes(codes[i]), 200, rep)
    update = best_per_frame_ms(lambda i: loc.update(winter[i]), 200, rep)
    t0 = time.perf_counter()
    front.encode(winter)
    batch = time.perf_counter() - t0
    print(f"encode one image: {encode:.3f} ms")
    print(f"score_codes one code against {N_PLACES:,} places: {score:.3f} ms")
    print(f"Localizer.update kenyon+cann: {update:.3f} ms ({1e3 / update:,.0f} frames/s)")
    print(f"encode a batch of {len(winter)} frames: {1e3 * batch:.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
