"""Indexes over compact codes side by side: build time, query time, recall of the exact top k.

Usage::

    python benchmarks/scale_indexes.py --places N [--places N ...] --json FILE [--data DIR]
        [--queries Q] [--k K] [--skip NAME] [--skip NAME ...]

Protocol: the map of ``benchmarks/scale.py`` (the Nordland 64x32 summer codes, 256 bits,
tiled to N places, tile flip 0.25, place flip 0.02), built in memory; ``--queries`` (default
200) winter frames at random places of the map, each seen on its tile.  For every index of
:data:`flyvpr.large.INDEXES` (faiss ones only with ``flyvpr[faiss]`` installed): build
seconds, query milliseconds one query at a time and per query in one batch, the share of the
exact top ``k`` (default 100, from ``exhaustive``) that the index returns
(``recall_top_k``), and the share of queries whose true place (within 20) is in its top k
(``true_place_in_top_k``).  Threads: numba's and faiss's defaults (2 on the 2-core machine).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks import scale  # noqa: E402


def measure(name, factory, codes, queries, truth, exact, k) -> dict:
    index = factory()
    t0 = time.perf_counter()
    index.build(codes)
    build_s = time.perf_counter() - t0
    index.search(queries[:1], k)  # warm up
    t0 = time.perf_counter()
    single = [index.search(q, k)[0][0] for q in queries]
    single_ms = 1e3 * (time.perf_counter() - t0) / len(queries)
    t0 = time.perf_counter()
    places, _ = index.search(queries, k)
    batch_ms = 1e3 * (time.perf_counter() - t0) / len(queries)
    recall = np.mean([len(np.intersect1d(p, e)) / k for p, e in zip(places, exact, strict=True)])
    found = np.mean(
        [np.any(np.abs(p[p >= 0] - t) <= 20) for p, t in zip(places, truth, strict=True)]
    )
    del single
    return {
        "index": name,
        "build_s": build_s,
        "query_ms_single": single_ms,
        "query_ms_batched": batch_ms,
        "recall_top_k": float(recall),
        "true_place_in_top_k": float(found),
        "index_mb": index.nbytes / 2**20,
    }


WHAT = "benchmarks/scale_indexes.py, this 2-core machine"


def run_line(places, queries: int, k: int, skip=()) -> str:
    """How a run was made, as its options (the output and data folders left out)."""
    parts = [f"--places {n}" for n in places] + [f"--queries {queries}", f"--k {k}"]
    return " ".join(parts + [f"--skip {name}" for name in skip])


def read_document(path: Path) -> dict:
    """An earlier run's JSON for ``--append``; ValueError naming ``path`` if it is not one."""
    import json

    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--append: cannot read {path} as JSON ({exc})") from None
    rows = data.get("rows") if isinstance(data, dict) else None
    keys = ("places", "index", "k")
    if not isinstance(rows, list) or not all(
        isinstance(r, dict) and all(k in r for k in keys) for r in rows
    ):
        raise ValueError(
            f"--append: {path} is not a document of this benchmark (an object whose 'rows' "
            "each give places, index and k)"
        )
    return data


def document(rows: list[dict], run: str, earlier: dict | None = None) -> dict:
    """The JSON of a run's ``rows`` so far: with ``earlier`` (a document of this benchmark),
    its rows and runs first, less the rows this run measured again (same places, index and
    k)."""
    runs, kept = [], []
    if earlier is not None:
        mine = {(r["places"], r["index"], r["k"]) for r in rows}
        runs = list(earlier.get("runs", []))
        kept = [r for r in earlier["rows"] if (r["places"], r["index"], r["k"]) not in mine]
    return {"what": WHAT, "runs": runs + [run], "rows": kept + rows}


def render_table(data: dict) -> str:
    """The rows side by side, in the order run, then each line of ``runs`` (how they were
    made: which indexes were stopped or left out, and why)."""
    lines = [
        "| places | index | queries | build s | ms per query, single | ms per query, batched | "
        "recall@k | true in top k | index MB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    notes: list[str] = []
    for r in data["rows"]:
        mark = ""
        if r.get("note"):
            if r["note"] not in notes:
                notes.append(r["note"])
            mark = f" ({notes.index(r['note']) + 1})"
        lines.append(
            f"| {r['places']:,} | {r['index']}{mark} | {r['queries']} | {r['build_s']:.2f} | "
            f"{r['query_ms_single']:.3f} | {r['query_ms_batched']:.3f} | "
            f"{r['recall_top_k']:.3f} | {r['true_place_in_top_k']:.3f} | {r['index_mb']:.0f} |"
        )
    ks = sorted({r["k"] for r in data["rows"]})
    lines += ["", f"k = {', '.join(map(str, ks))}."]
    if data.get("runs"):
        lines += ["", "Runs:", ""] + [f"- {run}" for run in data["runs"]]
    for i, note in enumerate(notes):
        lines += ["", f"({i + 1}) {note}."]
    return "\n".join(lines)


def main(argv=None) -> int:
    from flyvpr._io import write_json_atomic
    from flyvpr.large import (
        INDEXES,
        ExhaustiveIndex,
        MultiIndexHash,
        open_large_map,
        tile_queries,
        write_tiled_map,
    )

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--places", type=int, action="append", required=True)
    p.add_argument("--queries", type=int, default=200)
    p.add_argument("--k", type=int, default=100)
    p.add_argument("--skip", action="append", default=[], help="index names to leave out")
    p.add_argument("--json", type=Path, required=True)
    p.add_argument(
        "--append",
        action="store_true",
        help="keep the rows and runs already in --json (rows measured again are replaced)",
    )
    p.add_argument("--data", type=Path, default=scale.DEFAULT_DATA)
    args = p.parse_args(argv)
    earlier = None
    if args.append and args.json.exists():
        try:
            earlier = read_document(args.json)
        except ValueError as exc:
            p.error(str(exc))
    run = run_line(args.places, args.queries, args.k, args.skip)
    summer, winter = scale.load_frames(args.data)
    enc = scale.fit_encoder(summer)
    winter_codes = enc.encode(winter)
    factories = {
        "exhaustive": ExhaustiveIndex,
        "mih r1": lambda: MultiIndexHash(radius=1),
        "mih r2": lambda: MultiIndexHash(radius=2),
    }
    try:
        import faiss  # noqa: F401

        factories["faiss-ivf"] = INDEXES["faiss-ivf"]
        factories["faiss-hnsw"] = INDEXES["faiss-hnsw"]
    except ImportError:
        print("faiss not installed: pip install 'flyvpr[faiss]'; its indexes are left out")
    rows = []
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory(prefix="flyvpr-indexes-") as tmp:
        for n in args.places:
            path = write_tiled_map(
                Path(tmp) / "m.fvmap",
                enc.reference_codes_,
                n,
                scale.TILE_FLIP,
                scale.PLACE_FLIP,
                random_state=0,
            )
            codes = np.array(open_large_map(path).codes)  # in memory: faiss copies anyway
            truth = rng.integers(0, n, args.queries)
            queries = np.concatenate(
                [
                    tile_queries(winter_codes[t % 2400][None], t // 2400, scale.TILE_FLIP)
                    for t in truth
                ]
            )
            exact, _ = ExhaustiveIndex().build(codes).search(queries, args.k)
            for name, factory in factories.items():
                if name in args.skip:
                    continue
                row = {"places": n, "k": args.k, "queries": args.queries}
                row.update(measure(name, factory, codes, queries, truth, exact, args.k))
                rows.append(row)
                # (written after every row: a run stopped later keeps what it measured)
                write_json_atomic(args.json, document(rows, run, earlier))
                print(
                    f"{n:>10,} {name:11s} build {row['build_s']:7.2f} s  single "
                    f"{row['query_ms_single']:8.3f} ms  batched {row['query_ms_batched']:8.3f} ms"
                    f"  recall@{args.k} {row['recall_top_k']:.3f}  true in top "
                    f"{row['true_place_in_top_k']:.3f}  {row['index_mb']:.0f} MB",
                    flush=True,
                )
            del codes
    write_json_atomic(args.json, document(rows, run, earlier))
    return 0


if __name__ == "__main__":
    sys.exit(main())
