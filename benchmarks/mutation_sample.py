"""Sampled mutation testing: one operator or constant of a module changed at a time.

Usage::

    python benchmarks/mutation_sample.py src/flyvpr/temporal/cann/_filter.py \\
        --tests tests/test_cann_filter.py [--sample 150] [--seed 0] [--jobs 2] [--json FILE]

Protocol: every mutation point of the module is listed from its syntax tree (docstrings left
out): an arithmetic operator swapped (``+``/``-``, ``*``/``/``, ``//`` -> ``/``, ``**`` ->
``*``, ``%`` -> ``//``), a comparison turned (``<``/``<=``, ``>``/``>=``, ``==``/``!=``,
``is``/``is not``), ``and``/``or`` swapped, an integer constant plus one or a float constant
times 1.5 (0.0 -> 1.0).  ``--sample`` of them, drawn with ``random.Random(seed)``, are applied
one at a time to a copy of ``src/`` and ``tests/`` and the given tests run against each
(``pytest -x``); a mutant is killed when they fail.  numba's kernels stay compiled (the module
mutated is plain Python), so a mutant costs one run of the tests.  mutmut (configured in
``pyproject.toml``, see CONTRIBUTING) mutates more kinds of things but needs the kernels
uncompiled; this is the quick check a change of a core module is held to.
"""

from __future__ import annotations

import argparse
import ast
import os
import random
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_SWAP = {
    ast.Add: ("+", "-"),
    ast.Sub: ("-", "+"),
    ast.Mult: ("*", "/"),
    ast.Div: ("/", "*"),
    ast.FloorDiv: ("//", "/"),
    ast.Pow: ("**", "*"),
    ast.Mod: ("%", "//"),
}
_TURN = {
    ast.Lt: ("<", "<="),
    ast.LtE: ("<=", "<"),
    ast.Gt: (">", ">="),
    ast.GtE: (">=", ">"),
    ast.Eq: ("==", "!="),
    ast.NotEq: ("!=", "=="),
    ast.IsNot: ("is not", "is"),
    ast.Is: ("is", "is not"),
}


@dataclass(frozen=True)
class Mutant:
    start: int  # character offsets in the module's text
    end: int
    text: str
    line: int

    def describe(self, source: str) -> str:
        return f"line {self.line}: {source[self.start : self.end]} -> {self.text}"


def mutants(source: str) -> list[Mutant]:
    """Every mutation point of ``source`` (see the module docstring), in the tree's order."""
    tree = ast.parse(source)
    starts = [0]
    for line in source.splitlines(keepends=True):
        starts.append(starts[-1] + len(line))

    def at(line: int, col: int) -> int:
        return starts[line - 1] + col

    docstrings = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr):
            if isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
                docstrings.add(id(body[0].value))

    def between(left: ast.AST, right: ast.AST, old: str, new: str, line: int) -> list[Mutant]:
        a = at(left.end_lineno, left.end_col_offset)  # type: ignore[attr-defined]
        b = at(right.lineno, right.col_offset)  # type: ignore[attr-defined]
        i = source.find(old, a, b)
        return [Mutant(i, i + len(old), new, line)] if i >= 0 else []

    out: list[Mutant] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and type(node.op) in _SWAP:
            out += between(node.left, node.right, *_SWAP[type(node.op)], node.lineno)
        elif isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in _TURN:
            out += between(node.left, node.comparators[0], *_TURN[type(node.ops[0])], node.lineno)
        elif isinstance(node, ast.BoolOp):
            old, new = ("and", "or") if isinstance(node.op, ast.And) else ("or", "and")
            out += between(node.values[0], node.values[1], old, new, node.lineno)
        elif (
            isinstance(node, ast.Constant)
            and id(node) not in docstrings
            and type(node.value) in (int, float)
            and node.lineno == node.end_lineno
        ):
            value = node.value
            new = repr(value + 1) if isinstance(value, int) else repr(value * 1.5 or 1.0)
            a, b = at(node.lineno, node.col_offset), at(node.lineno, node.end_col_offset)
            out.append(Mutant(a, b, new, node.lineno))
    return out


def _copy_tree() -> Path:
    """A scratch copy of the sources and tests that one worker mutates in place."""
    work = Path(tempfile.mkdtemp(prefix="flyvpr-mutants-"))
    for name in ("src", "tests"):
        shutil.copytree(ROOT / name, work / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", work)
    return work


def _run(work: Path, module: str, source: str, mutant: Mutant, tests: list[str]) -> str:
    text = source[: mutant.start] + mutant.text + source[mutant.end :]
    try:
        compile(text, module, "exec")
    except SyntaxError:
        return "invalid"
    target = work / module
    target.write_text(text, encoding="utf-8")
    try:
        env = dict(os.environ, PYTHONPATH=str(work / "src"))
        run = subprocess.run(
            [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests],
            cwd=work,
            env=env,
            capture_output=True,
            timeout=900,
        )
        return "killed" if run.returncode != 0 else "survived"
    except subprocess.TimeoutExpired:
        return "killed"  # a mutant that hangs the tests is caught by them
    finally:
        target.write_text(source, encoding="utf-8")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("module", help="the module to mutate, relative to the repository root")
    p.add_argument("--tests", nargs="+", required=True, help="the module's own tests")
    p.add_argument("--sample", type=int, default=150, help="mutants to run (default 150)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample (default 0)")
    p.add_argument("--jobs", type=int, default=2, help="mutants run side by side (default 2)")
    p.add_argument("--json", type=Path, help="also write every mutant's outcome as JSON")
    args = p.parse_args(argv)
    if args.sample < 1:
        p.error(f"--sample must be at least 1; got {args.sample}")
    path = ROOT / args.module
    if not path.is_file() or path.suffix != ".py":
        print(f"module not found (a .py file under the repository): {path}", file=sys.stderr)
        return 1
    missing = [t for t in args.tests if not (ROOT / t.split("::")[0]).exists()]
    if missing:
        print(f"tests not found: {', '.join(missing)}", file=sys.stderr)
        return 1
    source = path.read_text(encoding="utf-8")
    try:
        points = mutants(source)
    except SyntaxError as exc:
        print(f"{args.module} does not parse: {exc}", file=sys.stderr)
        return 1
    chosen = random.Random(args.seed).sample(points, min(args.sample, len(points)))
    print(f"{args.module}: {len(points)} mutation points; running {len(chosen)} (seed {args.seed})")
    jobs = max(1, args.jobs)
    trees = [_copy_tree() for _ in range(jobs)]
    # The tests must pass on the module as it is, or every mutant would count as killed.
    baseline = Mutant(0, 0, "", 0)
    if _run(trees[0], args.module, source, baseline, args.tests) != "survived":
        for tree in trees:
            shutil.rmtree(tree, ignore_errors=True)
        print(f"the tests fail on {args.module} unchanged: fix them first", file=sys.stderr)
        return 1
    outcomes: dict[int, str] = {}

    def worker(k: int) -> None:
        for i in range(k, len(chosen), jobs):
            outcomes[i] = _run(trees[k], args.module, source, chosen[i], args.tests)
            print(f"{outcomes[i]:9s} {chosen[i].describe(source)}", flush=True)

    try:
        with ThreadPoolExecutor(jobs) as pool:
            list(pool.map(worker, range(jobs)))
    finally:
        for tree in trees:
            shutil.rmtree(tree, ignore_errors=True)
    valid = [i for i in outcomes if outcomes[i] != "invalid"]
    killed = sum(outcomes[i] == "killed" for i in valid)
    share = killed / len(valid) if valid else float("nan")
    invalid = len(chosen) - len(valid)
    print(f"killed {killed} of {len(valid)} mutants ({share:.3f}); {invalid} invalid")
    if args.json:
        record = {
            "benchmark": "mutation-sample",
            "module": args.module,
            "tests": args.tests,
            "seed": args.seed,
            "points": len(points),
            "killed": killed,
            "valid": len(valid),
            "mutants": [
                {"mutant": chosen[i].describe(source), "outcome": outcomes[i]}
                for i in sorted(outcomes)
            ],
        }
        from flyvpr._io import write_json_atomic

        write_json_atomic(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
