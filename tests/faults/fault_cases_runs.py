"""Fault battery cases on runs: outputs, usage errors, signals and full disks, evidence.

Each case is a function ``(ctx) -> (ok, observed)``; see ``faults.py`` for the runner.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import stat
import time

import numpy as np

import fault_fixtures as fx
from faults import SHARED_DATA, Case, Run, evaluate_args, refused, succeeded

CASES: list[Case] = []


def case(case_id: str, group: str, expected: str):
    def register(fn):
        CASES.append(Case(case_id, group, expected, fn))
        return fn

    return register


# -- outputs: only what the user named is touched -----------------------------------------------
def _output_is_input(target, extra_args=(), dataset="generic", build=fx.generic_dataset):
    def run(ctx):
        root = build(ctx.dir / "data")
        out = target(root, ctx)
        extra = extra_args(root, ctx)
        before = fx.snapshot(ctx.dir)
        argv = evaluate_args(root, *extra, "--out", out, dataset=dataset)
        result = ctx.cli(argv)
        return refused(ctx, result, 2, ["--out", out.name], before=before)

    return run


def _model_args(root, ctx):
    model = ctx.dir / "model.npz"
    fit = ["fit", "--dataset", "generic", "--root", root, "--method", "flyhash"]
    ctx.cli([*fit, "--save", model, "--quiet", "--no-cache"])
    return ["--load", model]


def _csv_args(root, ctx):
    return ["--positions-csv", "positions.csv", "--radius", "5"]


case("outputs/out-is-a-query-image", "outputs", "exit 2 naming --out; image unchanged")(
    _output_is_input(lambda root, ctx: root / "query" / "003.png", lambda r, c: [])
)
case("outputs/out-is-the-loaded-model", "outputs", "exit 2; model unchanged")(
    _output_is_input(lambda root, ctx: ctx.dir / "model.npz", _model_args)
)


def _with_csv(path):
    fx.generic_dataset(path)
    fx.positions_csv(path)
    return path


case("outputs/out-is-the-positions-csv", "outputs", "exit 2; CSV unchanged")(
    _output_is_input(lambda root, ctx: root / "positions.csv", _csv_args, build=_with_csv)
)
case("outputs/out-is-the-ground-truth", "outputs", "exit 2; ground_truth.npy unchanged")(
    _output_is_input(
        lambda root, ctx: root / "ground_truth.npy",
        lambda r, c: [],
        dataset="vprbench",
        build=fx.vprbench_dataset,
    )
)


@case("outputs/save-is-a-reference-image", "outputs", "fit --save onto an input: exit 2")
def _save_input(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    target = root / "reference" / "000.png"
    before = fx.snapshot(ctx.dir)
    argv = ["fit", "--dataset", "generic", "--root", root, "--method", "flyhash", "--quiet"]
    result = ctx.cli([*argv, "--no-cache", "--save", target])
    return refused(ctx, result, 2, ["--save", "000.png"], before=before)


def _special_output(make, name):
    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        cache = ctx.dir / "cache"
        out = make(ctx.dir / name)
        before = fx.snapshot(ctx.dir)
        argv = evaluate_args(root, "--out", out)
        argv.remove("--no-cache")
        result = ctx.cli([*argv, "--cache-dir", cache])
        ok, observed = refused(ctx, result, 2, ["--out", name], before=before)
        if cache.exists():  # the refusal must come before any image is decoded
            ok, observed = False, observed + " [decoded images before refusing]"
        return ok, observed

    return run


def _fifo(path):
    os.mkfifo(path)
    # a reader end keeps a (wrong) writer from blocking the battery
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    _KEEP.append(fd)
    return path


_KEEP: list = []

for _id, _make, _name in (
    ("outputs/out-is-a-fifo", _fifo, "pipe.json"),
    ("outputs/out-is-a-folder", lambda p: (p.mkdir(), p)[1], "folder.json"),
    ("outputs/out-is-a-device-link", lambda p: (os.symlink("/dev/null", p), p)[1], "null.json"),
    ("outputs/out-folder-under-a-file", lambda p: (p.write_text("x"), p / "r.json")[1], "file"),
    ("outputs/out-name-too-long", lambda p: p.parent / ("r" * 251 + ".json"), "r" * 20),
):
    case(_id, "outputs", "exit 2 naming --out, before decoding anything")(
        _special_output(_make, _name)
    )


@case("outputs/out-folder-missing", "outputs", "exit 0; the folders made when written")
def _missing_folders(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    out = ctx.dir / "a" / "b" / "result.json"
    result = ctx.cli(evaluate_args(root, "--out", out))
    return succeeded(ctx, result, lambda: (out.is_file() and not fx.leftovers(ctx.dir), "written"))


@case("outputs/out-name-250-characters", "outputs", "exit 0; written, no temporary file left")
def _long_name(ctx):
    # The temporary file beside it once took the whole name plus 14 bytes: over NAME_MAX.
    root = fx.generic_dataset(ctx.dir / "data")
    out = ctx.dir / ("r" * 245 + ".json")
    result = ctx.cli(evaluate_args(root, "--out", out))
    return succeeded(ctx, result, lambda: (out.is_file() and not fx.leftovers(ctx.dir), "written"))


@case("outputs/out-folder-read-only", "outputs", "exit 2 before work, or written if root")
def _read_only(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    folder = ctx.dir / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    out = folder / "result.json"
    try:
        result = ctx.cli(evaluate_args(root, "--out", out))
        if os.access(folder, os.W_OK):  # root writes anyway
            ok, text = succeeded(ctx, result, lambda: (out.is_file(), "written"))
            return ok, text + " (running as root: the folder is writable)"
        return refused(ctx, result, 2, ["--out", "ro"])
    finally:
        folder.chmod(0o755)


@case("outputs/out-is-a-symlink", "outputs", "exit 0; the link's target written, link kept")
def _symlink(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    target = ctx.dir / "target.json"
    target.write_text("old")
    link = ctx.dir / "link.json"
    os.symlink(target, link)
    result = ctx.cli(evaluate_args(root, "--out", link))

    def check():
        kept = link.is_symlink() and os.readlink(link) == str(target)
        written = "auc" in target.read_text()
        return kept and written, f"link kept: {kept}; target holds the result: {written}"

    return succeeded(ctx, result, check)


@case("outputs/new-file-mode", "outputs", "new --out file 0644 under umask 022")
def _mode(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    out = ctx.dir / "result.json"
    old = os.umask(0o022)
    try:
        result = ctx.cli(evaluate_args(root, "--out", out))
    finally:
        os.umask(old)
    mode = stat.S_IMODE(out.stat().st_mode) if out.exists() else None
    return succeeded(ctx, result, lambda: (mode == 0o644, f"mode {mode:o}" if mode else "no file"))


@case("outputs/existing-file-keeps-mode", "outputs", "an existing 0600 --out stays 0600")
def _keep_mode(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    out = ctx.dir / "result.json"
    out.write_text("old")
    out.chmod(0o600)
    result = ctx.cli(evaluate_args(root, "--out", out))
    mode = stat.S_IMODE(out.stat().st_mode)
    return succeeded(ctx, result, lambda: (mode == 0o600, f"mode {mode:o}"))


@case("outputs/disk-full", "outputs", "exit 1 naming the file; no .tmp, no partial file")
def _disk_full(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    out = ctx.dir / "result.json"

    def limit():  # the file size limit makes write() fail with EFBIG, as a full disk would
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (512, 512))

    proc = ctx.subprocess(
        evaluate_args(root, "--out", out), preexec_fn=limit, env={"PYTHONDONTWRITEBYTECODE": "1"}
    )
    _, err = proc.communicate(timeout=300)
    run = Run(proc.returncode, "", err, "Traceback" in err and err or None)
    return refused(ctx, run, 1, ["result.json"], outputs=[out])


# -- usage errors: exit 2 naming the option -----------------------------------------------------
def _usage(argv_tail, option, dataset="generic", command="evaluate", root_needed=True):
    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        if command == "evaluate":
            argv = evaluate_args(root, *argv_tail, dataset=dataset)
            if not root_needed:
                i = argv.index("--root")
                del argv[i : i + 2]
        else:
            argv = [command, *argv_tail]
        before = fx.snapshot(ctx.dir)
        result = ctx.cli(argv)
        return refused(ctx, result, 2, [option], before=before)

    return run


USAGE = [
    ("usage/count-0", ["--count", "0"], "--count"),
    ("usage/first-negative", ["--first", "-1"], "--first"),
    ("usage/tolerance-negative", ["--tolerance", "-1"], "--tolerance"),
    ("usage/seed-negative", ["--seed", "-1"], "--seed"),
    ("usage/radius-negative", ["--positions-csv", "p.csv", "--radius", "-1"], "--radius"),
    ("usage/radius-without-csv", ["--radius", "5"], "--radius"),
    (
        "usage/tolerance-with-csv",
        ["--positions-csv", "p.csv", "--radius", "5", "--tolerance", "2"],
        "--tolerance",
    ),  # fmt: skip
    (
        "usage/param-random-state-vs-seed",
        ["--param", "random_state=5", "--seed", "0"],
        "random_state",
    ),  # fmt: skip
    ("usage/param-nan", ["--param", "sampling_ratio=NaN"], "sampling_ratio"),
]
for _id, _tail, _opt in USAGE:
    case(_id, "usage", f"exit 2 naming {_opt}")(_usage(_tail, _opt))

case("usage/nordland-without-root", "usage", "exit 2 naming --root")(
    _usage([], "--root", dataset="nordland", root_needed=False)
)
case("usage/spacing-0", "usage", "exit 2 naming --spacing")(
    _usage(["--reference", "a", "--query", "b", "--spacing", "0"], "--spacing", "robotcar")
)
for _speed in ("0", "nan", "inf", "2-1"):
    case(f"usage/speed-{_speed}", "usage", "exit 2 naming --speed")(
        _usage(["--dataset", "generic", "--speed", _speed], "--speed", command="localize")
    )
case("usage/places-0", "usage", "exit 2 naming --places")(
    _usage(["--places", "0"], "--places", command="demo")
)
case("usage/jobs-0", "usage", "exit 2 naming --jobs")(
    _usage(["cfg.toml", "--out", "x", "--jobs", "0"], "--jobs", command="experiment")
)


@case("data/csv-latin1-byte", "data", "exit 1 naming positions.csv and the line")
def _latin1(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    fx.positions_csv(root, latin1=True)
    before = fx.snapshot(ctx.dir)
    result = ctx.cli(evaluate_args(root, "--positions-csv", "positions.csv", "--radius", "5"))
    return refused(ctx, result, 1, ["positions.csv", "line"], before=before)


@case("data/csv-utf8-bom", "data", "exit 0; a positions CSV with a BOM is read")
def _bom(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    fx.positions_csv(root, bom=True)
    result = ctx.cli(evaluate_args(root, "--positions-csv", "positions.csv", "--radius", "5"))
    return succeeded(ctx, result)


@case("library/localizer-before-fit", "library", "NotFittedError naming each call")
def _localizer(ctx):
    from flyvpr import NotFittedError
    from flyvpr.localization import Localizer

    loc = Localizer("flyhash")
    named = []
    for call, fn in (
        ("update", lambda: loc.update(np.zeros((32, 64)))),
        ("scores", lambda: loc.scores(np.zeros((32, 64)))),
        ("n_places", lambda: loc.n_places),
    ):
        try:
            fn()
        except NotFittedError as exc:
            named.append(call in str(exc))
        except Exception as exc:  # anything else is the failure being looked for
            return False, f"{call}: {type(exc).__name__}: {exc}"
    return all(named) and len(named) == 3, f"{sum(named)} of 3 calls named in the error"


# -- signals: SIGTERM unwinds, nothing half-written -----------------------------------------
def _sigterm(watch, argv_of, expected_tmp: bool):
    """Start the CLI in a subprocess; send SIGTERM when ``watch(ctx)`` says so."""

    def run(ctx):
        argv = argv_of(ctx)
        proc = ctx.subprocess(argv, env={"FLYVPR_CACHE_DIR": str(ctx.dir / "default-cache")})
        seen_tmp = False
        deadline = time.monotonic() + 240
        while proc.poll() is None and time.monotonic() < deadline:
            fired, seen_tmp = watch(ctx)
            if fired:
                proc.send_signal(signal.SIGTERM)
                break
            time.sleep(0.001)
        _, err = proc.communicate(timeout=120)
        run_ = Run(proc.returncode, "", err, err if "Traceback" in err else None)
        outs = [ctx.dir / "result.json", ctx.dir / "model.npz"]
        ok, observed = refused(ctx, run_, 143, ["SIGTERM"], outputs=outs)
        if expected_tmp and not seen_tmp:
            return None, observed + " (the write ended before the signal: inconclusive)"
        return ok, observed + (" (signal sent while a .tmp existed)" if seen_tmp else "")

    return run


def _when_tmp(ctx):
    tmp = fx.leftovers(ctx.dir)
    return bool(tmp), bool(tmp)


def _after(seconds):
    start = []

    def watch(ctx):
        start.append(time.monotonic()) if not start else None
        return time.monotonic() - start[0] > seconds, False

    return watch


def _big_dataset(path):
    fx.write_folder(path / "reference", fx.frames(200, 0, size=(128, 256)))
    fx.write_folder(path / "query", fx.frames(4, 1, size=(128, 256)))


def _big(ctx):
    return ctx.shared_fixture("big-128x256", _big_dataset)


case("signals/sigterm-while-computing", "signals", "exit 143, one line, nothing written")(
    _sigterm(
        _after(6.0),
        lambda ctx: evaluate_args(
            fx.generic_dataset(ctx.dir / "data"),
            "--param",
            "epochs=10000000",
            "--out",
            ctx.dir / "result.json",
            method="flynet",
        ),  # fmt: skip
        expected_tmp=False,
    )
)
case("signals/sigterm-while-writing-model", "signals", "exit 143; no .tmp, no model file")(
    _sigterm(
        _when_tmp,
        lambda ctx: [
            "fit",
            "--dataset",
            "generic",
            "--root",
            _big(ctx),
            "--method",
            "pixels",
            "--size",
            "128x256",
            "--save",
            ctx.dir / "model.npz",
            "--quiet",
            "--no-cache",
        ],  # fmt: skip
        expected_tmp=True,
    )
)
case("signals/sigterm-while-writing-cache", "signals", "exit 143; no .tmp in the cache")(
    _sigterm(
        _when_tmp,
        lambda ctx: [
            "fit",
            "--dataset",
            "generic",
            "--root",
            _big(ctx),
            "--method",
            "flyhash",
            "--size",
            "128x256",
            "--save",
            ctx.dir / "model.npz",
            "--quiet",
            "--cache-dir",
            ctx.dir / "cache",
        ],  # fmt: skip
        expected_tmp=True,
    )
)


# -- evidence: no confident answer without evidence (branches cann and bench) ----------------
BLANK_METHODS = ("pixels", "flyhash", "flynet", "kenyon", "pixels+cann", "flyhash+cann",
                 "flynet+cann", "kenyon+cann", "kenyon+seqslam", "flynet+seqslam",
                 "seqslam")  # fmt: skip


def _blank(path):
    blank = np.full((500, 32, 64), 128, np.uint8)
    fx.write_folder(path / "reference", blank)
    fx.write_folder(path / "query", blank)


def _blank_case(method):
    def run(ctx):
        root = ctx.shared_fixture("blank-500", _blank)
        out = ctx.dir / "result.json"
        result = ctx.cli(
            evaluate_args(root, "--tolerance", "20", "--out", out, "--seed", "0", method=method)
        )

        def check():
            r = json.loads(out.read_text())
            auc, rp = r["auc"], r["recall_at_100_precision"]
            return auc <= 0.1 and rp == 0, f"AUC {auc:.3f}, R@100%P {rp:.3f}"

        return succeeded(ctx, result, check)

    return run


for _m in BLANK_METHODS:
    case(f"evidence/blank-frames-{_m}", "evidence", "AUC <= 0.1 and R@100%P = 0")(_blank_case(_m))


def _distinct(path):
    fx.write_folder(path / "reference", fx.frames(500, 0))
    fx.write_folder(path / "query", fx.frames(500, 1, noise=8.0))


@case("evidence/zero-weight-model", "evidence", "flynet+cann with zero weights: AUC <= 0.1")
def _zero_weights(ctx):
    root = ctx.shared_fixture("distinct-500", _distinct)
    model = ctx.dir / "model.npz"
    fit = ["fit", "--dataset", "generic", "--root", root, "--method", "flynet+cann"]
    ctx.cli([*fit, "--save", model, "--quiet", "--no-cache"])
    meta, arrays = fx.read_model(model)
    arrays["frontend/weights_"] = np.zeros_like(arrays["frontend/weights_"])
    fx.write_model(model, meta, arrays)
    out = ctx.dir / "result.json"
    result = ctx.cli(
        evaluate_args(
            root, "--load", model, "--tolerance", "20", "--out", out, method="flynet+cann"
        )
    )

    def check():
        r = json.loads(out.read_text())
        return r["auc"] <= 0.1 and r["recall_at_100_precision"] == 0, (
            f"AUC {r['auc']:.3f}, R@100%P {r['recall_at_100_precision']:.3f}"
        )

    return succeeded(ctx, result, check)


@case("evidence/seqslam-nordland-300-499-seed1", "evidence",
      "flynet+seqslam: no place > 10% of frames, AUC >= 0.5")  # fmt: skip
def _seqslam(ctx):
    root = SHARED_DATA / "nordland_64x32"
    if not root.is_dir():
        return None, f"data not found at {root}"
    common = [
        "--dataset", "nordland", "--root", root, "--reference", "summer", "--query", "winter",
        "--first", "300", "--count", "200", "--seed", "1", "--method", "flynet+seqslam",
        "--quiet", "--cache-dir", ctx.dir / "cache",
    ]  # fmt: skip
    out, csv_out = ctx.dir / "result.json", ctx.dir / "frames.csv"
    ev = ctx.cli(["evaluate", *common, "--out", out])
    lo = ctx.cli(["localize", *common, "--out", csv_out])
    if lo.code != 0:
        return succeeded(ctx, lo)

    def check():
        auc = json.loads(out.read_text())["auc"]
        places = np.loadtxt(csv_out, delimiter=",", skiprows=1, usecols=2).astype(int)
        share = np.bincount(places).max() / places.size
        text = f"AUC {auc:.3f}; most predicted place {share:.0%} of frames"
        return auc >= 0.5 and share <= 0.10, text

    return succeeded(ctx, ev, check)
