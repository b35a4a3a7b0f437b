"""Fault battery cases on inputs: image folders and pixels, caches, model files, resources.

Each case is a function ``(ctx) -> (ok, observed)`` registered with :func:`case`; see
``faults.py`` for the runner and the standard checks.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

import fault_fixtures as fx
from faults import REPO, Case, evaluate_args, refused, succeeded

CASES: list[Case] = []


def case(case_id: str, group: str, expected: str):
    def register(fn):
        CASES.append(Case(case_id, group, expected, fn))
        return fn

    return register


# -- frames: every entry of an image folder is read correctly or refused by name ------------
def _folder_entry(make, name: str, code=1):
    """A query folder with one more entry ``name`` made by ``make(path)``: refused by name."""

    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        make(root / "query" / name)
        before = fx.snapshot(ctx.dir)
        out = ctx.dir / "result.json"
        result = ctx.cli(evaluate_args(root, "--out", out))
        return refused(ctx, result, code, [name], before=before, outputs=[out])

    return run


def _fifo(path):
    os.mkfifo(path)


def _gif(path):
    from PIL import Image

    Image.fromarray(fx.frames(1, 5)[0]).save(path)


ENTRY_CASES = [
    ("frames/dangling-symlink", "x.png", lambda p: os.symlink(p.parent / "gone.png", p)),
    ("frames/symlink-loop", "loop.png", lambda p: os.symlink(p, p)),
    ("frames/fifo", "pipe.png", _fifo),
    ("frames/device", "dev.png", lambda p: os.symlink("/dev/null", p)),
    ("frames/gif", "012.gif", _gif),
    ("frames/webp", "012.webp", _gif),
    ("frames/text-file", "notes.txt", lambda p: p.write_text("notes")),
    ("frames/sub-folder", "more", lambda p: p.mkdir()),
    ("frames/zero-byte-png", "012.png", lambda p: p.write_bytes(b"")),
    ("frames/png-14000x14000", "012.png", lambda p: fx.png_declaring(p, 14000, 14000)),
    ("frames/float-tiff-0-255", "012.tif", lambda p: fx.float_tiff(p, fx.frames(1, 3)[0])),
    (
        "frames/float-tiff-nan",
        "012.tif",
        lambda p: fx.float_tiff(p, np.where(np.eye(32, 64) > 0, np.nan, 0.5)),
    ),
]
for _id, _name, _make in ENTRY_CASES:
    case(_id, "frames", f"exit 1 naming {_name}; nothing written")(_folder_entry(_make, _name))


def _n_query(path: Path) -> int:
    return json.loads(path.read_text())["n_query"]


def _reads(make, name, expect_value=None, expect_n=fx.N_FRAMES + 1):
    """The extra entry is read: ``expect_n`` query frames, and its pixels as expected."""

    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        path = root / "query" / name
        make(path)
        out = ctx.dir / "result.json"
        result = ctx.cli(evaluate_args(root, "--out", out))

        def check():
            n = _n_query(out)
            text = f"{n} query frames read"
            if expect_value is not None:
                from flyvpr.images import load_image

                value = float(load_image(path).mean())
                text += f", pixel mean {value:.4f} (expected {expect_value:.4f})"
                if abs(value - expect_value) > 1e-4:
                    return False, text
            return n == expect_n, text

        return succeeded(ctx, result, check)

    return run


case("frames/hidden-file", "frames", "exit 0; hidden .DS_Store skipped (12 frames)")(
    _reads(lambda p: p.write_text("x"), ".DS_Store", expect_n=fx.N_FRAMES)
)
case("frames/float-tiff-0-1", "frames", "exit 0; float TIFF in [0, 1] read as is")(
    _reads(lambda p: fx.float_tiff(p, np.full((32, 64), 0.25)), "012.tif", 0.25)
)
case("frames/png-16bit", "frames", "exit 0; 16-bit PNG scaled by 65535")(
    _reads(lambda p: fx.png16(p, 40000), "012.png", 40000 / 65535)
)


@case("frames/unreadable-file", "frames", "exit 1 naming it, or read if the process may (root)")
def _unreadable(ctx):
    root = fx.generic_dataset(ctx.dir / "data")
    path = root / "query" / "012.png"
    fx.write_folder(ctx.dir / "x", fx.frames(1, 4))
    os.replace(ctx.dir / "x" / "000.png", path)
    path.chmod(0)
    if os.access(path, os.R_OK):  # root reads it anyway: then it must be read correctly
        return _read_as_root(ctx, root)
    before = fx.snapshot(ctx.dir)
    result = ctx.cli(evaluate_args(root))
    return refused(ctx, result, 1, ["012.png"], before=before)


def _read_as_root(ctx, root):
    out = ctx.dir / "result.json"
    result = ctx.cli(evaluate_args(root, "--out", out))
    ok, text = succeeded(ctx, result, lambda: (_n_query(out) == 13, f"{_n_query(out)} frames"))
    return ok, text + " (running as root: the file is readable)"


# -- caches: damaged entries are named and rebuilt; replaced pictures invalidate ---------------
def _cache_case(damage):
    """Populate the cache, damage its entries with ``damage(files, ctx)``, run again with -v:
    exit 0, a warning naming the entry, the same result as without a cache, entry rebuilt."""

    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        cache = ctx.dir / "cache"
        args = evaluate_args(root, "--out", ctx.dir / "clean.json")
        args.remove("--no-cache")
        first = ctx.cli([*args, "--cache-dir", cache])
        if first.code != 0:
            return False, f"first run failed: {first.err_lines[:1]}"
        files = sorted(cache.glob("*.npz"))
        named = damage(files, ctx)
        args[args.index("--out") + 1] = ctx.dir / "again.json"
        again = ctx.cli(["-v", *args, "--cache-dir", cache])

        def check():
            a = json.loads((ctx.dir / "clean.json").read_text())["auc"]
            b = json.loads((ctx.dir / "again.json").read_text())["auc"]
            warned = [ln for ln in again.err_lines if "cache" in ln and named.name in ln]
            third = ctx.cli([*args, "--cache-dir", cache])
            quiet = not [ln for ln in third.err_lines if "cache" in ln]
            text = (
                f"named: {bool(warned)}; AUC {b:.3f} vs {a:.3f} clean; "
                f"rebuilt entry used silently next run: {quiet}"
            )
            return bool(warned) and a == b and quiet, text

        return succeeded(ctx, again, check)

    return run


def _garbage(files, ctx):
    files[0].write_bytes(os.urandom(5000))
    return files[0]


def _swapped(files, ctx):
    files[0].write_bytes(files[1].read_bytes())
    return files[0]


def _zero_byte(files, ctx):
    files[0].write_bytes(b"")
    return files[0]


def _truncated(files, ctx):
    data = files[0].read_bytes()
    files[0].write_bytes(data[: len(data) // 2])
    return files[0]


def _rewritten(value):
    """A well-formed entry (right key, recomputed checksum) whose pixels are ``value``."""

    def damage(files, ctx):
        import zipfile

        from flyvpr.images import _write_cache

        with zipfile.ZipFile(files[0]) as zf:
            key = json.loads(zf.read("meta.json"))["key"]
            with zf.open("images.npy") as fh:
                arr = np.lib.format.read_array(fh)
        arr[0, 0, 0] = value
        _write_cache(files[0], arr, key)
        return files[0]

    return damage


for _id, _damage in (
    ("cache/garbage-entry", _garbage),
    ("cache/swapped-entry", _swapped),
    ("cache/zero-byte-entry", _zero_byte),
    ("cache/truncated-entry", _truncated),
    ("cache/nan-entry", _rewritten(np.nan)),
    ("cache/out-of-range-entry", _rewritten(2.0)),
):
    case(_id, "cache", "exit 0; entry named at -v, rebuilt; result as without cache")(
        _cache_case(_damage)
    )


@case("cache/picture-replaced-same-size-mtime", "cache", "exit 0; stale entry not used")
def _replaced(ctx):
    root = fx.generic_dataset(ctx.dir / "data", pattern="{i:03d}.bmp")  # size fixed by shape
    cache = ctx.dir / "cache"
    args = evaluate_args(root, "--out", ctx.dir / "a.json")
    args.remove("--no-cache")
    ctx.cli([*args, "--cache-dir", cache])
    target = root / "query" / "003.bmp"
    st = target.stat()
    other = root / "query" / "007.bmp"
    target.write_bytes(other.read_bytes())
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    same = target.stat().st_size == st.st_size and target.stat().st_mtime_ns == st.st_mtime_ns
    args[args.index("--out") + 1] = ctx.dir / "b.json"
    cached = ctx.cli([*args, "--cache-dir", cache])
    fresh = ctx.cli(evaluate_args(root, "--out", ctx.dir / "c.json"))

    def check():
        b = json.loads((ctx.dir / "b.json").read_text())["auc"]
        c = json.loads((ctx.dir / "c.json").read_text())["auc"]
        text = f"same size and mtime: {same}; AUC {b:.3f} with cache, {c:.3f} decoded afresh"
        return same and b == c, text

    ok, observed = succeeded(ctx, cached, check)
    return ok and fresh.code == 0, observed


# -- model files: crafted files (checksums recomputed) refused in one line ----------------------
def _honest_model(ctx, method="flynet"):
    root = fx.generic_dataset(ctx.dir / "data")
    model = ctx.dir / "model.npz"
    fit = [
        "fit", "--dataset", "generic", "--root", root, "--method", method,
        "--param", "epochs=5", "--save", model, "--quiet", "--no-cache",
    ]  # fmt: skip
    if method != "flynet":
        fit = fit[:7] + fit[9:]
    run = ctx.cli(fit)
    if run.code != 0:
        raise RuntimeError(f"fit failed: {run.err}")
    return root, model


def _model_case(edit, field_name, method="flynet"):
    def run(ctx):
        root, model = _honest_model(ctx, method)
        meta, arrays = fx.read_model(model)
        edit(meta, arrays)
        fx.write_model(model, meta, arrays)
        before = fx.snapshot(ctx.dir)
        out = ctx.dir / "result.json"
        result = ctx.cli(evaluate_args(root, "--load", model, "--out", out, method=method))
        result.err = result.err.replace("--method", "")
        return refused(ctx, result, 1, ["model.npz", field_name], before=before, outputs=[out])

    return run


def _drop_state(meta, arrays):
    del meta["frontend"]["state"]["weights_"]
    del arrays["frontend/weights_"]


def _drop_array(meta, arrays):
    del arrays["frontend/weights_"]


def _empty_state(meta, arrays):
    meta["frontend"]["state"] = {}
    arrays.clear()


def _dtype(meta, arrays):
    arrays["frontend/weights_"] = arrays["frontend/weights_"].astype(np.float64)


def _shape(meta, arrays):
    arrays["frontend/weights_"] = arrays["frontend/weights_"][:, :-1]


def _method_name(meta, arrays):
    meta["method"] = "flyhash"


def _param(meta, arrays):
    meta["frontend"]["params"]["n_hidden"] = 32


def _meta_field(meta, arrays):
    del meta["preprocessing"]


for _id, _edit, _field in (
    ("model/missing-state-key", _drop_state, "weights_"),
    ("model/missing-array-entry", _drop_array, "weights_"),
    ("model/empty-state", _empty_state, "frontend.state"),
    ("model/other-dtype", _dtype, "weights_"),
    ("model/other-shape", _shape, "weights_"),
    ("model/other-method-name", _method_name, "method"),
    ("model/param-contradicts-arrays", _param, "frontend"),
    ("model/missing-meta-field", _meta_field, "preprocessing"),
):
    case(_id, "model", f"exit 1 naming the file and {_field} (checksums recomputed)")(
        _model_case(_edit, _field)
    )


@case("model/byte-flipped", "model", "exit 1 naming the file (any byte, e.g. a zip timestamp)")
def _flipped(ctx):
    root, model = _honest_model(ctx)
    data = bytearray(model.read_bytes())
    data[10] ^= 0x01  # the first member's modification time: numpy never reads it
    model.write_bytes(bytes(data))
    before = fx.snapshot(ctx.dir)
    result = ctx.cli(evaluate_args(root, "--load", model, method="flynet"))
    return refused(ctx, result, 1, ["model.npz"], before=before)


@case("model/deflate-bomb", "model", "exit 1 naming the file and entry, before decompressing")
def _bomb(ctx):
    root, model = _honest_model(ctx)
    bomb = fx.bomb_model(model, ctx.dir / "bomb.npz")
    before = fx.snapshot(ctx.dir)
    result = ctx.cli(evaluate_args(root, "--load", bomb, method="flynet"))
    ok, observed = refused(ctx, result, 1, ["bomb.npz", "weights_"], before=before)
    return ok, f"{bomb.stat().st_size / 1e6:.1f} MB file claiming 1.07 GB: {observed}"


@case("model/npy-header-claims-huge-array", "model", "exit 1 naming ground_truth.npy, at once")
def _gt_header(ctx):
    root = fx.vprbench_dataset(ctx.dir / "data", gt_header_shape=(10**6, 10**6))
    before = fx.snapshot(ctx.dir)
    result = ctx.cli(evaluate_args(root, dataset="vprbench"))
    ok, observed = refused(ctx, result, 1, ["ground_truth.npy"], before=before)
    return ok and result.seconds < 10, f"{observed} ({result.seconds:.2f} s)"


@case("model/pickled-array", "model", "exit 1 naming the file; nothing unpickled")
def _pickled(ctx):
    root, model = _honest_model(ctx)
    meta, arrays = fx.read_model(model)
    fx.write_model(model, meta, arrays)
    import zipfile

    with zipfile.ZipFile(model, "a") as zf:  # an object array np.save would pickle
        with zf.open("frontend/evil.npy", "w") as fh:
            np.lib.format.write_array(fh, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    before = fx.snapshot(ctx.dir)
    result = ctx.cli(evaluate_args(root, "--load", model, method="flynet"))
    return refused(ctx, result, 1, ["model.npz"], before=before)


@case("model/bomb-peak-memory", "model", "peak RSS loading the bomb <= 2x an honest model's")
def _peak(ctx):
    root, model = _honest_model(ctx)
    bomb = fx.bomb_model(model, ctx.dir / "bomb.npz")
    code = (
        "import resource, sys\n"
        "from flyvpr.modelio import load_method\n"
        "try:\n    load_method(sys.argv[1])\nexcept ValueError:\n    pass\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    )
    peaks = {}
    for name, path in (("honest", model), ("bomb", bomb)):
        res = subprocess.run(
            [sys.executable, "-c", code, str(path)],
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": str(REPO / "src")},
            timeout=120,
        )
        peaks[name] = int(res.stdout.strip().splitlines()[-1]) / 1024  # kB -> MB
    ok = peaks["bomb"] <= 2 * peaks["honest"]
    return ok, f"peak RSS: honest model {peaks['honest']:.0f} MB, bomb {peaks['bomb']:.0f} MB"


# -- resources ----------------------------------------------------------------------------------
def _resource(argv_tail, names, dataset_args=True):
    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        argv = evaluate_args(root, *argv_tail) if dataset_args else list(argv_tail)
        before = fx.snapshot(ctx.dir)
        result = ctx.cli(argv)
        return refused(ctx, result, 1, names, before=before)

    return run


for _id, _tail, _names, _ds in (
    ("resources/size-100000x100000", ["--size", "100000x100000"], ["--size", "GB"], True),
    ("resources/demo-places-10M", ["demo", "--places", "10000000"], ["--places", "TB"], False),
    ("resources/n_hidden-1e9", ["--param", "n_hidden=1000000000"], ["n_hidden", "GB"], True),
):
    case(_id, "resources", f"exit 1 before allocating, naming {_names[0]} and the size")(
        _resource(_tail, _names, _ds)
    )


def _filter_param(method, param, name):
    def run(ctx):
        root = fx.generic_dataset(ctx.dir / "data")
        before = fx.snapshot(ctx.dir)
        result = ctx.cli(evaluate_args(root, "--param", param, method=method))
        return refused(ctx, result, 1, [name], before=before)

    return run


# 10**12 rather than 10**9: a grid of 10**9 offsets is 8 GB that a filter may allocate and
# fill before failing, and the battery must stay safe to run on a shared machine.
for _id, _method, _param_text, _name in (
    (
        "resources/sequence_length-1e12",
        "flyhash+seqslam",
        "sequence_length=" + str(10**12),
        "sequence_length",
    ),
    ("resources/v_step-1e-12", "flyhash+seqslam", "v_step=1e-12", "v_step"),
    (
        "resources/excitation_width-1e12",
        "flyhash+cann-paper",
        "excitation_width=1e12",
        "excitation_width",
    ),
):
    case(_id, "resources", f"exit 1 in one line naming {_name}")(
        _filter_param(_method, _param_text, _name)
    )


def _robotcar(kind):
    def run(ctx):
        root = ctx.dir / "data"
        long = 10**24 + 7
        if kind == "csv":
            fx.robotcar_run(root, "a", pose_stamp_text=str(long))
            name = "ins.csv"
        else:
            fx.robotcar_run(root, "a", stamps_us=[fx.T0_US + k * 10**6 for k in range(7)] + [long])
            name = str(long)
        fx.robotcar_run(root, "b")
        before = fx.snapshot(ctx.dir)
        argv = evaluate_args(root, "--reference", "a", "--query", "b", dataset="robotcar")
        result = ctx.cli(argv)
        return refused(ctx, result, 1, [name], before=before)

    return run


case("resources/robotcar-25-digit-csv-stamp", "resources", "exit 1 naming ins.csv and the line")(
    _robotcar("csv")
)
case("resources/robotcar-25-digit-file-name", "resources", "exit 1 naming the image file")(
    _robotcar("name")
)
