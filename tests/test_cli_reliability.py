"""The CLI's argument checks, output checks, SIGTERM and out-of-memory handling."""

import os
import signal

import numpy as np
import pytest
from PIL import Image

from flyvpr.cli import main


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    rng = np.random.default_rng(0)
    for role in ("reference", "query"):
        (root / role).mkdir()
        for i in range(6):
            img = rng.integers(0, 256, (32, 64), dtype=np.uint8)
            Image.fromarray(img).save(root / role / f"{i}.png")
    (root / "pos.csv").write_text(
        "traverse,filename,x,y\n"
        + "".join(f"{r},{i}.png,{i},0\n" for r in ("reference", "query") for i in range(6))
    )
    return root


def _args(root, *extra):
    return ["evaluate", "--dataset", "generic", "--root", str(root), "--method", "flyhash",
            "--quiet", "--no-cache", *extra]  # fmt: skip


@pytest.mark.parametrize(
    "extra, option",
    [
        (["--count", "0"], "--count"),
        (["--first", "-1"], "--first"),
        (["--tolerance", "-1"], "--tolerance"),
        (["--seed", "-1"], "--seed"),
        (["--size", "0x4"], "--size"),
        (["--radius", "5"], "--radius"),
        (["--positions-csv", "pos.csv"], "--positions-csv"),
        (["--positions-csv", "pos.csv", "--radius", "-1"], "--radius"),
        (["--positions-csv", "pos.csv", "--radius", "5", "--tolerance", "1"], "--tolerance"),
        (["--param", "random_state=5"], "random_state"),
        (["--param", "frontend.random_state=5"], "random_state"),
        (["--param", "n_hidden=Infinity"], "n_hidden"),
    ],
)
def test_usage_errors_exit_2_in_one_line_naming_the_option(data, capsys, extra, option):
    assert main(_args(data, *extra)) == 2
    err = capsys.readouterr().err
    assert option in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize(
    "argv, option",
    [
        (["localize", "--dataset", "generic", "--speed", "0"], "--speed"),
        (["localize", "--dataset", "generic", "--speed", "nan"], "--speed"),
        (["localize", "--dataset", "generic", "--speed", "inf"], "--speed"),
        (["localize", "--dataset", "generic", "--speed", "2-1"], "--speed"),
        (["localize", "--dataset", "generic", "--speed", "1-2-3"], "--speed"),
        (["demo", "--places", "0"], "--places"),
        (["demo", "--tolerance", "-2"], "--tolerance"),
        (["experiment", "c.toml", "--out", "x", "--jobs", "0"], "--jobs"),
        (["evaluate", "--dataset", "nordland", "--method", "pixels"], "--root"),
        (["evaluate", "--dataset", "robotcar", "--root", ".", "--spacing", "0"], "--spacing"),
    ],
)
def test_more_usage_errors(capsys, argv, option):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert option in err and len(err.strip().splitlines()) == 1, err


def test_outputs_are_checked_before_any_work(data, tmp_path, capsys):
    image = data / "query" / "2.png"
    before = image.read_bytes()
    assert main(_args(data, "--out", str(image))) == 2
    assert image.read_bytes() == before
    assert "--out" in capsys.readouterr().err
    cache = tmp_path / "cache"
    argv = [a for a in _args(data) if a != "--no-cache"]
    (tmp_path / "file").write_text("x")
    nowhere = tmp_path / "file" / "sub" / "r.json"
    assert main([*argv, "--cache-dir", str(cache), "--out", str(nowhere)]) == 2
    assert "file is not a folder" in capsys.readouterr().err
    assert not cache.exists()  # refused before a single image was decoded
    csv = data / "pos.csv"
    rc = main(_args(data, "--positions-csv", "pos.csv", "--radius", "3", "--out", str(csv)))
    assert rc == 2 and csv.read_text().startswith("traverse")


def test_out_with_a_name_of_250_characters_is_written(data, tmp_path, capsys):
    out = tmp_path / ("r" * 245 + ".json")
    assert main(_args(data, "--out", str(out))) == 0
    assert [p.name for p in tmp_path.iterdir()] == [out.name]
    assert '"auc"' in out.read_text()
    too_long = tmp_path / ("r" * 251 + ".json")
    assert main(_args(data, "--out", str(too_long))) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "file name too long (256 bytes" in err and err.count("\n") == 1


def test_out_in_missing_folders_creates_them_when_written(data, tmp_path, capsys):
    out = tmp_path / "a" / "b" / "c" / "r.json"
    assert main(_args(data, "--out", str(out))) == 0
    assert '"auc"' in out.read_text()
    # A run that fails before writing leaves no folder behind.
    bad_model = tmp_path / "bad.npz"
    bad_model.write_bytes(b"not a model")
    later = tmp_path / "x" / "y" / "r.json"
    assert main(_args(data, "--load", str(bad_model), "--out", str(later))) == 1
    assert "bad.npz" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_fit_save_onto_an_input_and_load_then_out_onto_the_model(data, tmp_path, capsys):
    fit = ["fit", "--dataset", "generic", "--root", str(data), "--method", "flyhash", "--quiet",
           "--no-cache"]  # fmt: skip
    assert main([*fit, "--save", str(data / "reference" / "0.png")]) == 2
    model = tmp_path / "m.npz"
    assert main([*fit, "--save", str(model)]) == 0
    before = model.read_bytes()
    assert main(_args(data, "--load", str(model), "--out", str(model))) == 2
    assert model.read_bytes() == before


def test_sigterm_unwinds_to_143_and_restores_the_handler(data, tmp_path, capsys, monkeypatch):
    import flyvpr.cli.evaluate as ev

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not interrupt")

    monkeypatch.setattr(ev, "evaluate_method", terminated)
    previous = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "r.json"
    assert main(_args(data, "--out", str(out))) == 143
    assert "SIGTERM" in capsys.readouterr().err and not out.exists()
    assert signal.getsignal(signal.SIGTERM) is previous


def test_memory_error_is_one_line_naming_the_sizing_options(data, capsys, monkeypatch):
    import flyvpr.cli.evaluate as ev

    def boom(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(ev, "evaluate_method", boom)
    assert main(_args(data, "--param", "n_hidden=64")) == 1
    err = capsys.readouterr().err
    assert "out of memory" in err and "n_hidden=64" in err and len(err.splitlines()) == 1


def test_oversized_run_refused_naming_size(data, capsys):
    assert main(_args(data, "--size", "100000x100000")) == 1
    err = capsys.readouterr().err
    assert "--size 100000x100000" in err and "would need" in err


def test_datasets_says_what_is_read(capsys):
    assert main(["datasets"]) == 0
    out = capsys.readouterr().out
    assert "hidden" in out and ".gif" in out and "[0, 1]" in out


@pytest.mark.parametrize(
    "param, message",
    [
        ("tolerance=-1", "tolerance must be >= 0; got -1"),
        ("odometry=wheel", "odometry must be one of ('scaled', 'exact'); got 'wheel'"),
    ],
)
def test_a_bad_filter_parameter_is_refused_before_the_map_is_built(
    data, tmp_path, capsys, monkeypatch, param, message
):
    # The CANN checks its parameters on reset; `flyvpr map` refuses them before fitting the
    # front end and writes nothing (before, the map was written and could not be loaded).
    from flyvpr.frontends.kenyon import KenyonEncoder

    fitted = []
    monkeypatch.setattr(KenyonEncoder, "_fit", lambda self, images: fitted.append(1), raising=True)
    out = tmp_path / "x.map"
    code = main(["map", str(data / "reference"), "--out", str(out), "--param", param, "-q"])
    err = capsys.readouterr().err
    assert code == 1 and message in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and not fitted
