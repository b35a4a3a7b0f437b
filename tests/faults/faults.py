"""Fault battery: bad inputs and faults run end to end through the CLI, with a verdict each.

Every case builds its own fixture in a fresh temporary folder, runs ``flyvpr.cli.main([...])``
in-process (or ``python -m flyvpr`` in a subprocess where a signal, a resource limit or a
peak-memory figure is involved), and compares what it observed with what the reliability
rules (``docs/guide/reliability.md``) promise: the exit code, one line on stderr that names
the file or option, no traceback, no input changed, no temporary file left, no output
written after a refusal, and for the cases that must succeed, the right result.  Verdicts are
computed from the observation; nothing is hard-coded.

Usage::

    python tests/faults/faults.py [--json benchmarks/faults.json] [--only PREFIX ...]
                                  [--markdown out.md] [--from-json faults.json]

Prints the table (case, class, expected, observed, verdict); exit status 0 when every case
is OK, 1 otherwise.  ``render_markdown(json.load(...))`` renders the table for the docs:
``python docs/generate_results.py`` puts it on the results page and, between the markers
below, on ``docs/guide/reliability.md``.
The cases live in ``fault_cases.py`` and ``fault_cases_runs.py``; fixtures in
``fault_fixtures.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import fault_fixtures as fx  # noqa: E402

#: where ../shared/data lies for a checkout at REPO
SHARED_DATA = REPO.parent / "shared" / "data"


@dataclass
class Run:
    """What one CLI run did."""

    code: int | None
    out: str
    err: str
    traceback: str | None = None
    seconds: float = 0.0

    @property
    def err_lines(self) -> list[str]:
        return [line for line in self.err.splitlines() if line.strip()]


@dataclass
class Case:
    id: str
    group: str
    expected: str
    run: object  # callable(Ctx) -> (ok: bool | None, observed: str)


@dataclass
class Ctx:
    """A case's folder and helpers."""

    dir: Path
    shared: Path
    notes: list = field(default_factory=list)

    def cli(self, argv: list) -> Run:
        """``flyvpr.cli.main(argv)`` in-process; stdout, stderr and log records captured."""
        from flyvpr.cli import main

        out, err = io.StringIO(), io.StringIO()
        root = logging.getLogger()
        saved = root.handlers[:], root.level
        root.handlers = []
        t0 = time.perf_counter()
        tb = None
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main([str(a) for a in argv])
            except BaseException:  # an escaped exception is what the battery looks for
                code = None
                tb = traceback.format_exc()
        root.handlers, _ = saved
        root.setLevel(saved[1])
        return Run(code, out.getvalue(), err.getvalue(), tb, time.perf_counter() - t0)

    def subprocess(self, argv: list, *, env=None, timeout=120, **kwargs) -> subprocess.Popen:
        """Start ``python -m flyvpr argv`` with this checkout's package first on the path."""
        full_env = dict(os.environ, PYTHONPATH=str(REPO / "src"), **(env or {}))
        return subprocess.Popen(
            [sys.executable, "-m", "flyvpr", *map(str, argv)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=full_env,
            cwd=self.dir,
            **kwargs,
        )

    def shared_fixture(self, name: str, build) -> Path:
        """A read-only fixture built once per battery run (``build(path)``)."""
        path = self.shared / name
        if not path.exists():
            tmp = self.shared / (name + ".building")
            build(tmp)
            tmp.rename(path)
        return path


def short(text: str, ctx: Ctx, limit: int = 170) -> str:
    """One line of output for the table: case folder paths shortened, length limited."""
    text = " ".join(text.split())
    for base in (str(ctx.dir), str(ctx.shared)):
        text = text.replace(base + os.sep, "").replace(base, ".")
    text = re.sub(r"/tmp/[\w./-]*/", "", text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# -- the standard checks -------------------------------------------------------------------------
def refused(ctx: Ctx, run: Run, code: int, names=(), *, before=None, outputs=()):
    """A refusal: exit ``code``, one stderr line naming every entry of ``names``, no traceback,
    nothing under the case folder changed (``before``), no output written, no temporary file."""
    problems = []
    if run.traceback:
        problems.append("traceback: " + run.traceback.strip().splitlines()[-1])
    if run.code != code:
        problems.append(f"exit {run.code}, not {code}")
    lines = run.err_lines
    if len(lines) != 1:
        problems.append(f"{len(lines)} lines on stderr")
    for name in names:
        if str(name) not in run.err:
            problems.append(f"does not name {name}")
    problems += unchanged(ctx, before, outputs)
    first = lines[0] if lines else "(nothing on stderr)"
    observed = f"exit {run.code}: {short(first, ctx)}"
    return not problems, observed + (" [" + "; ".join(problems) + "]" if problems else "")


def unchanged(ctx: Ctx, before, outputs=()) -> list[str]:
    problems = []
    if before is not None:
        after = fx.snapshot(ctx.dir)
        changed = sorted(p for p in set(before) | set(after) if before.get(p) != after.get(p))
        if changed:
            problems.append("changed: " + ", ".join(short(p, ctx, 60) for p in changed[:3]))
    for out in outputs:
        if Path(out).exists() and (before is None or str(out) not in before):
            problems.append(f"wrote {short(str(out), ctx, 60)}")
    tmp = fx.leftovers(ctx.dir)
    if tmp:
        problems.append("left " + short(tmp[0], ctx, 60))
    return problems


def succeeded(ctx: Ctx, run: Run, check=None):
    """Exit 0 and no traceback; ``check()`` returns (ok, text) about the result."""
    problems = []
    if run.traceback:
        problems.append("traceback: " + run.traceback.strip().splitlines()[-1])
    if run.code != 0:
        problems.append(f"exit {run.code}: {short(' '.join(run.err_lines[:1]), ctx)}")
    text = ""
    if not problems and check is not None:
        ok, text = check()
        if not ok:
            problems.append(text)
            text = ""
    observed = "exit 0" + (f": {text}" if text else "") if not problems else ""
    return not problems, observed or "; ".join(problems)


def evaluate_args(root, *extra, method="flyhash", dataset="generic"):
    return [
        "evaluate", "--dataset", dataset, "--root", root, "--method", method,
        "--quiet", "--no-cache", *extra,
    ]  # fmt: skip


# -- running --------------------------------------------------------------------------------
def all_cases() -> list[Case]:
    import fault_cases
    import fault_cases_runs

    return [*fault_cases.CASES, *fault_cases_runs.CASES]


def run_case(case: Case, workdir: Path, shared: Path) -> dict:
    """Run one case in ``workdir/<id>``; returns its row of the table."""
    folder = workdir / case.id
    folder.mkdir(parents=True)
    ctx = Ctx(folder, shared)
    t0 = time.perf_counter()
    try:
        ok, observed = case.run(ctx)
    except Exception as exc:  # the case itself broke: report it, never hide it
        ok, observed = False, f"battery error: {type(exc).__name__}: {short(str(exc), ctx)}"
    verdict = "OK" if ok else ("n/a" if ok is None else "FAIL")
    return {
        "case": case.id,
        "class": case.group,
        "expected": case.expected,
        "observed": observed,
        "verdict": verdict,
        "seconds": round(time.perf_counter() - t0, 2),
    }


def run_battery(only=(), workdir: Path | None = None, progress=None) -> dict:
    """Run every case (or those whose id starts with one of ``only``); returns the JSON data."""
    cases = [c for c in all_cases() if not only or c.id.startswith(tuple(only))]
    with tempfile.TemporaryDirectory(prefix="flyvpr-faults-") as tmp:
        base = Path(workdir or tmp)
        shared = base / "_shared"
        shared.mkdir(parents=True, exist_ok=True)
        rows = []
        for case in cases:
            row = run_case(case, base, shared)
            rows.append(row)
            if progress:
                progress(row)
    import flyvpr

    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("OK", "FAIL", "n/a")}
    return {
        "benchmark": "flyvpr fault battery (tests/faults/faults.py)",
        "flyvpr_version": flyvpr.__version__,
        "commit": _commit(),
        "python": platform.python_version(),
        "platform": platform.platform(terse=True),
        "as_root": hasattr(os, "geteuid") and os.geteuid() == 0,
        "counts": counts,
        "cases": rows,
    }


def _commit() -> str | None:
    """The checkout's commit (with ``+dirty`` for uncommitted changes), if git is there."""
    try:
        head = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "")


def render_markdown(data: dict) -> str:
    """The battery's table as Markdown (for ``docs/guide/reliability.md``)."""
    c = data["counts"]
    lines = [
        f"{len(data['cases'])} cases: {c.get('OK', 0)} OK, {c.get('FAIL', 0)} FAIL, "
        f"{c.get('n/a', 0)} not applicable (flyvpr {data['flyvpr_version']}"
        + (f", commit {data['commit']}" if data.get("commit") else "")
        + f", Python {data['python']}, {data['platform']}"
        + (", as root" if data.get("as_root") else "")
        + ").",
        "",
        "| case | class | expected | observed | verdict |",
        "|---|---|---|---|---|",
    ]

    def cell(text) -> str:
        return str(text).replace("|", "\\|").replace("\n", " ")

    for r in data["cases"]:
        lines.append(
            f"| {cell(r['case'])} | {cell(r['class'])} | {cell(r['expected'])} | "
            f"{cell(r['observed'])} | {cell(r['verdict'])} |"
        )
    return "\n".join(lines) + "\n"


#: markers around the generated table in docs/guide/reliability.md
DOC_BEGIN = (
    "<!-- BEGIN faults table: generated from benchmarks/faults.json by faults.render_markdown -->"
)
DOC_END = "<!-- END faults table -->"


def render_text(data: dict) -> str:
    rows = [("case", "class", "expected", "observed", "verdict")]
    keys = ("case", "class", "expected", "observed", "verdict")
    rows += [tuple(r[k] for k in keys) for r in data["cases"]]
    widths = [min(max(len(r[i]) for r in rows), cap) for i, cap in enumerate((34, 10, 48, 90, 7))]
    out = []
    for r in rows:
        cells = [s if len(s) <= w else s[: w - 1] + "~" for s, w in zip(r, widths, strict=True)]
        out.append("  ".join(s.ljust(w) for s, w in zip(cells, widths, strict=True)).rstrip())
    c = data["counts"]
    out.append(f"\n{len(data['cases'])} cases: {c['OK']} OK, {c['FAIL']} FAIL, {c['n/a']} n/a")
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the results as JSON")
    parser.add_argument("--markdown", type=Path, help="write the table as Markdown")
    parser.add_argument("--only", nargs="*", default=(), help="case id prefixes to run")
    parser.add_argument("--keep", type=Path, help="run in this folder and keep it")
    parser.add_argument(
        "--from-json", type=Path, help="render an earlier run's JSON instead of running"
    )
    args = parser.parse_args(argv)

    def show(row):
        print(f"{row['verdict']:>4}  {row['case']}  ({row['seconds']:.1f} s)", file=sys.stderr)

    if args.from_json:
        data = json.loads(args.from_json.read_text())
    else:
        data = run_battery(args.only, args.keep, progress=show)
    print(render_text(data))
    if args.json:
        args.json.write_text(json.dumps(data, indent=2) + "\n")
    if args.markdown:
        args.markdown.write_text(render_markdown(data))
    return 0 if data["counts"]["FAIL"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
