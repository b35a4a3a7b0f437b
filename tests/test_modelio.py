import json
import zipfile

import numpy as np
import pytest

from flyvpr import modelio
from flyvpr.cli import main
from flyvpr.methods import METHODS, make_method, method_names
from flyvpr.modelio import FORMAT_VERSION, ModelFileError, load_method, save_method

CORE = [m for m in method_names(available_only=True) if not METHODS[m].extras]


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(0)
    ref = rng.random((40, 32, 64), dtype=np.float32)
    qry = np.clip(ref + rng.normal(0, 0.1, ref.shape).astype(np.float32), 0, 1)
    return ref, qry


@pytest.mark.parametrize("name", CORE)
def test_roundtrip_is_exact(tmp_path, data, name):
    ref, qry = data
    params = {"epochs": 5} if METHODS[name].frontend == "flynet" else None
    model = make_method(name, 0, frontend_params=params).fit(ref)
    S = model.score(qry)
    path = save_method(model, tmp_path / "m.npz")
    again = load_method(path)
    assert again.name == name
    np.testing.assert_array_equal(again.score(qry), S)
    assert again.footprint() == model.footprint()


def _rewrite(path, mutate):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    mutate(arrays)
    np.savez(path, **arrays)


def test_tampered_weights_refused(tmp_path, data):
    path = save_method(make_method("flynet", 0, {"epochs": 3}).fit(data[0]), tmp_path / "m.npz")

    def flip(arrays):
        arrays["frontend/weights_"] = arrays["frontend/weights_"] + np.float32(0.5)

    _rewrite(path, flip)
    with pytest.raises(ValueError, match="checksum"):
        load_method(path)


def _meta_edit(path, edit):
    def mutate(arrays):
        meta = json.loads(arrays["__meta__"].tobytes())
        edit(meta)
        arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)

    _rewrite(path, mutate)


def test_metadata_with_an_integer_past_pythons_digit_limit_is_a_model_file_error(tmp_path, data):
    # json.loads raises a plain ValueError there ("Exceeds the limit (4300 digits)"), which
    # named no file and was no ModelFileError
    from flyvpr.modelio import ModelFileError

    path = save_method(make_method("flyhash", 0).fit(data[0]), tmp_path / "m.npz")

    def huge(arrays):
        text = (
            arrays["__meta__"]
            .tobytes()
            .decode()
            .replace('"format_version": ', '"format_version": ' + "9" * 5000 + ', "x": ', 1)
        )
        arrays["__meta__"] = np.frombuffer(text.encode(), dtype=np.uint8)

    _rewrite(path, huge)
    with pytest.raises(ModelFileError, match="metadata is not valid JSON") as info:
        load_method(path)
    assert str(path) in str(info.value)


def test_wrong_format_version_refused(tmp_path, data):
    path = save_method(make_method("flyhash", 0).fit(data[0]), tmp_path / "m.npz")
    _meta_edit(path, lambda m: m.update(format_version=FORMAT_VERSION + 1))
    with pytest.raises(ValueError, match="format version"):
        load_method(path)


def test_other_image_size_refused(tmp_path, data):
    path = save_method(make_method("flyhash", 0).fit(data[0]), tmp_path / "m.npz")
    with pytest.raises(ValueError, match="32x64"):
        load_method(path, size=(16, 32))


def test_not_a_model_file(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, a=np.zeros(3))
    with pytest.raises(ValueError, match="not a flyvpr model|no flyvpr metadata"):
        load_method(p)
    q = tmp_path / "y.npz"
    q.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="not a readable"):
        load_method(q)
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        load_method(tmp_path / "missing.npz")


def test_pickled_arrays_are_never_loaded(tmp_path, data):
    path = save_method(make_method("flyhash", 0).fit(data[0]), tmp_path / "m.npz")

    def add_object(arrays):
        arrays["frontend/evil"] = np.array([{"x": 1}], dtype=object)

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    add_object(arrays)
    np.savez(path, **arrays)  # np.savez pickles object arrays
    with pytest.raises(ValueError):
        load_method(path)


def test_flyhash_connections_are_bit_packed_on_disk(tmp_path, data):
    path = save_method(make_method("flyhash", 0).fit(data[0]), tmp_path / "m.npz")
    with zipfile.ZipFile(path) as z:
        sizes = {i.filename: i.file_size for i in z.infolist()}
    assert sizes["frontend/connections_bits.npy"] < 64 * 2048 // 8 + 200


def test_cli_fit_save_load(tmp_path):
    from flyvpr.synthetic import make_route, save_route

    root = tmp_path / "route"
    save_route(make_route(n_places=40, random_state=0), root)
    model = tmp_path / "m.npz"
    common = [
        "--dataset",
        "nordland",
        "--root",
        str(root),
        "--reference",
        "summer",
        "--quiet",
        "--no-cache",
    ]
    assert (
        main(["fit", *common, "--method", "flynet", "--param", "epochs=5", "--save", str(model)])
        == 0
    )
    out1, out2 = tmp_path / "a.json", tmp_path / "b.json"
    ev = ["evaluate", *common, "--query", "winter", "--tolerance", "2"]
    assert main([*ev, "--load", str(model), "--out", str(out1)]) == 0
    assert main([*ev, "--method", "flynet", "--param", "epochs=5", "--out", str(out2)]) == 0
    a, b = json.loads(out1.read_text()), json.loads(out2.read_text())
    assert a["auc"] == b["auc"] and a["precision"] == b["precision"]
    assert main([*ev, "--load", str(model), "--size", "16x32"]) == 1


def test_rnn_roundtrip(tmp_path, data):
    pytest.importorskip("torch")
    ref, qry = data
    model = make_method(
        "flynet+rnn",
        0,
        frontend_params={"epochs": 5},
        filter_params={"epochs": 1, "hidden_size": 16},
    ).fit(ref)
    S = model.score(qry)
    again = load_method(save_method(model, tmp_path / "m.npz"))
    np.testing.assert_array_equal(again.score(qry), S)


@pytest.mark.parametrize("name", ["fc", "cnn"])
def test_torch_frontend_roundtrip(tmp_path, data, name):
    pytest.importorskip("torch")
    ref, qry = data
    model = make_method(name, 0, frontend_params={"epochs": 3}).fit(ref)
    S = model.score(qry)
    again = load_method(save_method(model, tmp_path / "m.npz"))
    np.testing.assert_allclose(again.score(qry), S, rtol=1e-6, atol=1e-7)


def test_a_file_from_before_an_added_parameter_loads_with_its_default(tmp_path, data, monkeypatch):
    # A map or model saved before the CANN's `odometry` existed has no such parameter: it
    # loads with the default.  Any other parameter missing is still refused.
    from flyvpr.temporal.cann import CANN

    model = make_method("flyhash+cann", 0).fit(data[0])
    older = [n for n in CANN._param_names() if n != "odometry"]
    with monkeypatch.context() as m:
        m.setattr(CANN, "_param_names", classmethod(lambda cls: older))
        path = save_method(model, tmp_path / "old.npz")
    again = load_method(path)
    assert again.filter.odometry == "scaled"
    np.testing.assert_array_equal(again.score(data[1]), model.score(data[1]))
    fewer = [n for n in older if n != "tolerance"]
    with monkeypatch.context() as m:
        m.setattr(CANN, "_param_names", classmethod(lambda cls: fewer))
        path = save_method(model, tmp_path / "older.npz")
    with pytest.raises(ValueError, match=r"filter\.params\.tolerance: missing"):
        load_method(path)


def test_a_file_from_before_jitter_loads_with_the_default_and_a_saved_one_is_kept(
    tmp_path, data, monkeypatch
):
    from flyvpr.temporal.cann import CANN

    model = make_method("flyhash+cann", 0).fit(data[0])
    model.filter.set_params(jitter=0.2)
    older = [n for n in CANN._param_names() if n != "jitter"]
    with monkeypatch.context() as m:
        m.setattr(CANN, "_param_names", classmethod(lambda cls: older))
        path = save_method(model, tmp_path / "old.npz")
    assert load_method(path).filter.jitter == CANN().jitter == 0.0
    again = load_method(save_method(model, tmp_path / "new.npz"))
    assert again.filter.jitter == 0.2
    np.testing.assert_array_equal(again.score(data[1]), model.score(data[1]))


@pytest.mark.parametrize("added", ["snap", "adapt_front"])
def test_a_file_from_before_a_filter_flag_runs_without_it(tmp_path, data, monkeypatch, added):
    from flyvpr.temporal.cann import CANN

    model = make_method("kenyon+cann", 0).fit(data[0])
    assert getattr(model.filter, added) is True
    older = [n for n in CANN._param_names() if n != added]
    with monkeypatch.context() as m:
        m.setattr(CANN, "_param_names", classmethod(lambda cls: older))
        path = save_method(model, tmp_path / "old.npz")
    loaded = load_method(path).filter
    assert getattr(loaded, added) is False
    assert all(getattr(loaded, k) is True for k in ("snap", "adapt_front") if k != added)
    assert getattr(load_method(save_method(model, tmp_path / "new.npz")).filter, added) is True


@pytest.mark.parametrize("name, held", [("flyhash+cann", False), ("pixels+cann", True)])
def test_a_file_from_before_hold_repeats_takes_the_front_ends_default(
    tmp_path, data, monkeypatch, name, held
):
    # without the parameter in the file, the filter holds repeated rows unless its front end's
    # scores repeat on sensor noise (as make_method sets it); a saved value is kept as it is
    from flyvpr.temporal.cann import CANN

    model = make_method(name, 0).fit(data[0])
    assert model.filter.hold_repeats is held
    older = [n for n in CANN._param_names() if n != "hold_repeats"]
    with monkeypatch.context() as m:
        m.setattr(CANN, "_param_names", classmethod(lambda cls: older))
        m.setattr(modelio, "_filter_extra", lambda filt: {})  # (files then said no root)
        path = save_method(model, tmp_path / "old.npz")
    assert load_method(path).filter.hold_repeats is held
    # its calibration table was given at raw confidences (such files say no root): resampled
    # at their fourth roots, the loaded filter maps the raw confidences 0, 0.1 ** 4, ... as
    # the old one did
    from flyvpr.temporal.cann._filter import _KNOTS as _K
    from flyvpr.temporal.cann._filter import table_at_roots

    old = model.filter.calibration
    loaded = load_method(path).filter.calibration
    assert tuple(loaded) == table_at_roots(old, 1)
    np.testing.assert_allclose(loaded, np.interp(_K**4, _K, old), rtol=0, atol=1e-15)
    model.filter.set_params(hold_repeats=not held)
    again = load_method(save_method(model, tmp_path / "new.npz"))
    assert again.filter.hold_repeats is (not held)
    assert tuple(again.filter.calibration) == tuple(old)  # a new file's table is kept
    # a file with hold_repeats but no root gave it at the raw confidence's square root
    with monkeypatch.context() as m:
        m.setattr(modelio, "_filter_extra", lambda filt: {})
        path = save_method(model, tmp_path / "square.npz")
    loaded = load_method(path).filter.calibration
    assert tuple(loaded) == table_at_roots(old, 2)
    np.testing.assert_allclose(loaded, np.interp(_K**2, _K, old), rtol=0, atol=1e-15)
    for bad in (3, "4", True, None):
        with monkeypatch.context() as m:
            m.setattr(modelio, "_filter_extra", lambda filt, bad=bad: {"calibration_root": bad})
            path = save_method(model, tmp_path / "bad.npz")
        with pytest.raises(ModelFileError, match=r"filter\.calibration_root: .*1, 2 or 4 expected"):
            load_method(path)
    # a filter section with anything else in it is refused, naming what it may hold
    with monkeypatch.context() as m:
        m.setattr(modelio, "_filter_extra", lambda filt: {"calibration_rot": 4})
        path = save_method(model, tmp_path / "typo.npz")
    with pytest.raises(
        ModelFileError,
        match=r"filter: must hold exactly name, params and state \(and may hold calibration_root\)",
    ):
        load_method(path)
    # a filter without a table (the paper's attractor) says no root and loads as it was
    from flyvpr.temporal import FILTERS

    assert modelio._filter_extra(FILTERS["cann-paper"]()) == {}
    assert modelio._filter_extra(CANN()) == {"calibration_root": 4}
    paper = make_method("flyhash+cann-paper", 0).fit(data[0])
    again = load_method(save_method(paper, tmp_path / "paper.npz"))
    assert again.filter.get_params().keys() == paper.filter.get_params().keys()
    S = paper.score(data[1])
    np.testing.assert_array_equal(again.filter.filter(S), paper.filter.filter(S))


def test_the_seed_a_method_was_made_with_is_kept(tmp_path, data):
    from flyvpr.modelio import _write_archive

    ref = data[0]
    path = save_method(make_method("kenyon+cann", 3).fit(ref), tmp_path / "m.npz")
    assert load_method(path).seed == 3
    # a Generator, or none: nothing to record
    rng = np.random.default_rng(3)
    path = save_method(make_method("kenyon+cann", rng).fit(ref), tmp_path / "g.npz")
    assert load_method(path).seed is None
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "__meta__"}
        meta = json.loads(z["__meta__"].tobytes())
    assert meta["seed"] is None
    for bad in ("3", -1, True, 2.0):
        meta["seed"] = bad
        out = _write_archive(tmp_path / "bad.npz", dict(meta), arrays)  # checksums recomputed
        with pytest.raises(ModelFileError, match=r"bad\.npz: seed: expected an integer >= 0"):
            load_method(out)


def test_only_a_method_is_saved(tmp_path):
    from flyvpr.large import CompactEncoder

    for thing in (CompactEncoder(), "kenyon+cann", None):
        with pytest.raises(TypeError, match=r"method must be a flyvpr Method .*; got"):
            save_method(thing, tmp_path / "m.npz")
    assert not (tmp_path / "m.npz").exists()


def _resealed(path, out, edit):
    """``path``'s metadata edited by ``edit`` and written to ``out`` with checksums recomputed
    (a crafted file: only the checks on the content can refuse it)."""
    from flyvpr.modelio import _write_archive

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "__meta__"}
        meta = json.loads(z["__meta__"].tobytes())
    edit(meta)
    return _write_archive(out, meta, arrays)


@pytest.fixture(scope="module")
def saved(tmp_path_factory, data):
    """Model files of a few methods (fitted once), by method name."""
    folder = tmp_path_factory.mktemp("saved")
    made = {}

    def get(name):
        if name not in made:
            made[name] = save_method(make_method(name, 0).fit(data[0]), folder / f"{name}.npz")
        return made[name]

    return get


@pytest.mark.parametrize(
    "name, part, key, value, problem",
    [
        ("kenyon", "frontend", "wavelength", 1e308,
         r"frontend\.state: does not restore a kenyon \(wavelength must be in \[2\.0, "
         r"1000000\.0\] pixels; got 1e\+308\)"),
        ("seqslam", "filter", "v_max", 1e308,
         r"filter\.state: does not restore a seqslam \(v_min=0\.8 to v_max=1e\+308 in steps "
         r"of v_step=0\.1 are more velocities than can be counted"),
        ("seqslam", "filter", "v_min", -1e308, r"filter\.state: .*more velocities than can"),
        ("seqslam", "filter", "sequence_length", 10**30,
         r"filter\.state: does not restore a seqslam \(.*sequence_length=10+ would need"),
    ],
)  # fmt: skip
def test_parameters_that_overflow_are_a_model_file_error(
    tmp_path, saved, name, part, key, value, problem
):
    # (each raised OverflowError from deep inside the part)
    out = _resealed(
        saved(name), tmp_path / "x.npz", lambda m: m[part]["params"].update({key: value})
    )
    with pytest.raises(ModelFileError, match=rf"x\.npz: {problem}"):
        load_method(out)


@pytest.mark.parametrize(
    "name, key, value",
    [("flyhash+cann-paper", "movement", 1e308), ("seqslam", "v_step", 1e30)],
)
def test_huge_but_valid_parameters_load_and_score(tmp_path, saved, data, name, key, value):
    # movement 1e308 moves the packet off the route every frame (it overflowed int64);
    # v_step 1e30 searches one velocity
    out = _resealed(
        saved(name), tmp_path / "x.npz", lambda m: m["filter"]["params"].update({key: value})
    )
    model = load_method(out)
    assert getattr(model.filter, key) == value
    assert np.isfinite(model.score(data[1][:5])).all()


def test_a_parameter_given_as_an_array_is_saved_as_a_list(tmp_path, data):
    # velocities=np.arange(...) fitted, then save_method refused it ("cannot save attribute
    # velocities of type ndarray")
    velocities = np.arange(0.75, 2.01, 0.125)
    model = make_method("flyhash+cann-paper", 0, filter_params={"velocities": velocities})
    model.fit(data[0])
    again = load_method(save_method(model, tmp_path / "m.npz"))
    assert again.filter.velocities == velocities.tolist()
    np.testing.assert_array_equal(again.score(data[1]), model.score(data[1]))
    ints = make_method("flyhash+cann-paper", 0, filter_params={"velocities": np.arange(1, 3)})
    again = load_method(save_method(ints.fit(data[0]), tmp_path / "i.npz"))
    assert again.filter.velocities == [1, 2]


@pytest.mark.parametrize("where", ["local header", "central directory", "member data"])
def test_a_damaged_sealed_file_says_it_failed_its_checksum(tmp_path, saved, where):
    # one bit flipped in the zip's local header or central directory was reported as "has no
    # flyvpr metadata: not a flyvpr model", though the file's checksum told it was damaged
    path = saved("flyhash")
    body = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("__meta__.npy")
        at = {
            "local header": info.header_offset,
            "central directory": z.start_dir,
            "member data": info.header_offset + 40 + len(info.filename) + 64,
        }[where]
    body[at] ^= 0x10
    out = tmp_path / "damaged.npz"
    out.write_bytes(bytes(body))
    with pytest.raises(
        ModelFileError,
        match=r"damaged\.npz failed its file checksum: it was modified or is damaged",
    ):
        load_method(out)
    # a file without the seal is no flyvpr model, as before
    plain = tmp_path / "plain.npz"
    np.savez(plain, a=np.zeros(3))
    with pytest.raises(ModelFileError, match="not a flyvpr model"):
        load_method(plain)
