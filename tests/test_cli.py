import json

import numpy as np
import pytest

from flyvpr.cli import main
from flyvpr.synthetic import make_route, save_route


@pytest.fixture(scope="module")
def route_dir(route_folder):
    return route_folder(60)


def _eval_args(root, *extra):
    return [
        "evaluate",
        "--dataset",
        "nordland",
        "--root",
        str(root),
        "--reference",
        "summer",
        "--query",
        "winter",
        "--tolerance",
        "2",
        "--quiet",
        "--no-cache",
        *extra,
    ]


REQUIRED = {
    "method",
    "dataset",
    "reference",
    "query",
    "first",
    "count",
    "n_reference",
    "n_query",
    "tolerance",
    "seed",
    "auc",
    "recall_at_1",
    "recall_at_5",
    "recall_at_10",
    "recall_at_100_precision",
    "extended_precision",
    "precision",
    "recall",
    "train_accuracy",
    "timing",
    "footprint",
}


@pytest.mark.parametrize("method", ["pixels", "flyhash", "flynet"])
def test_evaluate_writes_json(route_dir, tmp_path, capsys, method):
    out = tmp_path / "r.json"
    rc = main(
        _eval_args(
            route_dir, "--method", method, "--seed", "1", "--out", str(out), "--param", "epochs=20"
        )
        if method == "flynet"
        else _eval_args(route_dir, "--method", method, "--seed", "1", "--out", str(out))
    )
    assert rc == 0
    data = json.loads(out.read_text())
    assert REQUIRED <= set(data)
    assert data["method"] == method and data["seed"] == 1 and data["n_query"] == 60
    assert data["tolerance"] == 2 and data["tolerance_unit"] == "frames"
    assert set(data["timing"]) >= {"load_s", "encode_s", "match_s", "per_query_ms"}
    assert set(data["footprint"]) == {"layers", "params", "neurons"}
    assert (data["train_accuracy"] is None) == (method != "flynet")
    assert 0 <= data["auc"] <= 1 and len(data["precision"]) == len(data["recall"])
    assert data["extended_precision"] == pytest.approx(
        (data["precision"][0] + data["recall_at_100_precision"]) / 2
    )
    printed = capsys.readouterr().out
    assert method in printed and "AUC" in printed
    header = next(line for line in printed.splitlines() if "AUC" in line)
    assert "R@100%P" in header and "EP" in header.split()


def test_evaluate_window(route_dir, tmp_path):
    out = tmp_path / "r.json"
    assert (
        main(
            _eval_args(
                route_dir, "--method", "pixels", "--first", "10", "--count", "20", "--out", str(out)
            )
        )
        == 0
    )
    data = json.loads(out.read_text())
    assert (data["first"], data["count"], data["n_reference"]) == (10, 20, 20)


def _route_with_positions(route_dir, folder, offset: float):
    """A copy of the route with a positions CSV: reference frame i at (10 i, 0), query frame
    i at (10 i + offset, 0)."""
    import shutil

    root = folder / "route"
    shutil.copytree(route_dir, root)
    lines = ["traverse,filename,x,y"]
    for role, season, shift in (("reference", "summer", 0.0), ("query", "winter", offset)):
        for i, path in enumerate(sorted((root / season).iterdir())):
            lines.append(f"{role},{path.name},{10 * i + shift},0")
    (root / "positions.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return root


def _generic_args(root, radius, *extra):
    return [
        "evaluate", "--dataset", "generic", "--root", str(root), "--reference", "summer",
        "--query", "winter", "--positions-csv", "positions.csv", "--radius", str(radius),
        "--method", "pixels", "--quiet", "--no-cache", *extra,
    ]  # fmt: skip


def test_evaluate_records_the_paths_resolved(route_dir, tmp_path, monkeypatch):
    # given relative to the working directory, recorded absolute: the JSON names the files
    # wherever it is read, as experiment run files do
    root = _route_with_positions(route_dir, tmp_path, offset=3.0)
    monkeypatch.chdir(tmp_path)
    assert main(_generic_args("route", 5, "--out", "r.json")) == 0
    protocol = json.loads((tmp_path / "r.json").read_text())["protocol"]
    assert protocol["root"] == str(root.resolve())
    assert protocol["sources"] == [str(root.resolve() / "positions.csv")]
    assert protocol["reference_dir"] == str(root.resolve() / "summer")


def test_evaluate_refuses_a_ground_truth_without_a_match_before_the_work(
    route_dir, tmp_path, capsys, monkeypatch
):
    import flyvpr.cli.evaluate as evaluate_cli

    root = _route_with_positions(route_dir, tmp_path, offset=3.0)
    monkeypatch.setattr(evaluate_cli, "evaluate_method", lambda *a, **k: pytest.fail("fitted"))
    out = tmp_path / "r.json"
    assert main(_generic_args(root, 1, "--out", str(out))) == 1
    err = capsys.readouterr().err
    assert err.startswith("flyvpr evaluate: error: the ground truth gives no query a true match")
    assert "(1.0 metres)" in err and err.count("\n") == 1
    assert not out.exists()


def test_corrupt_png_exits_1_naming_the_file(route_dir, tmp_path, capsys):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(route_dir, root)
    bad = root / "winter" / "images-00017.png"
    bad.write_bytes(bad.read_bytes()[:40])
    out = tmp_path / "r.json"
    rc = main(_eval_args(root, "--method", "pixels", "--out", str(out)))
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "images-00017.png" in err
    assert not out.exists()


def test_missing_root_exits_1(tmp_path, capsys):
    rc = main(_eval_args(tmp_path / "nope", "--method", "pixels"))
    assert rc == 1
    assert "nope" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv",
    [
        ["evaluate", "--dataset", "nordland", "--method", "no-such-method"],
        ["evaluate", "--dataset", "atlantis", "--method", "pixels"],
        ["no-such-command"],
        [],
    ],
)
def test_usage_errors_exit_2(argv, capsys):
    assert main(argv) == 2


def test_option_not_for_dataset_is_usage_error(route_dir, capsys):
    rc = main(_eval_args(route_dir, "--method", "pixels", "--spacing", "5"))
    assert rc == 2
    assert "--spacing" in capsys.readouterr().err


def test_unknown_param_is_usage_error(route_dir, capsys):
    rc = main(_eval_args(route_dir, "--method", "flynet", "--param", "bogus=1"))
    assert rc == 2
    assert "bogus" in capsys.readouterr().err


@pytest.mark.parametrize("key", ["epochs", "learning_rate", "batch_size"])
def test_a_param_both_parts_take_needs_its_prefix(route_dir, tmp_path, capsys, key):
    # flynet+rnn: FlyNet and the RNN both train; epochs=1 went to FlyNet alone and left the
    # RNN at its default without a word
    argv = ["fit", *_eval_args(route_dir)[1:], "--method", "flynet+rnn", "--param", f"{key}=1"]
    assert main([*argv, "--save", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err
    assert f"--param {key}: both parts of 'flynet+rnn' take {key!r}" in err
    assert f"frontend.{key}=" in err and f"filter.{key}=" in err
    assert not (tmp_path / "m.npz").exists()


def test_prefixed_params_go_to_their_part():
    from flyvpr.cli._common import split_params

    front, filt = split_params(
        "flynet+rnn", [("frontend.epochs", 3), ("filter.epochs", 2), ("hidden_size", 16)]
    )
    assert front == {"epochs": 3} and filt == {"epochs": 2, "hidden_size": 16}
    # a name only one part takes needs no prefix
    assert split_params("flynet+cann", [("epochs", 5)]) == ({"epochs": 5}, {})


def test_help_exits_0(capsys):
    assert main(["--help"]) == 0
    assert "evaluate" in capsys.readouterr().out
    assert main(["evaluate", "--help"]) == 0


def test_datasets_lists_every_loader(capsys):
    from flyvpr.datasets import DATASETS

    assert main(["datasets"]) == 0
    out = capsys.readouterr().out
    for name in DATASETS:
        assert f"{name}:" in out


def test_methods_lists_parts_within_a_terminal_width(capsys):
    from flyvpr.frontends import FRONTENDS
    from flyvpr.temporal import FILTERS

    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    for name in [*FRONTENDS, *FILTERS]:
        assert f"  {name} " in out
    assert max(len(line) for line in out.splitlines()) <= 100


def test_methods_all_lists_every_name_once(capsys):
    from flyvpr.methods import METHODS

    assert main(["methods", "--all"]) == 0
    names = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert names == list(METHODS)


def test_closed_pipe_ends_quietly():
    """`flyvpr methods | head`: no traceback and no message when the reader goes away."""
    import subprocess
    import sys

    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from flyvpr.cli import main; sys.exit(main(sys.argv[1:]))",
        ]
        + ["methods", "--all"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # the reader leaves before the first line is written
    err = proc.stderr.read().decode()
    proc.wait(timeout=60)
    proc.stderr.close()
    assert err == ""
    assert proc.returncode == 141


def test_demo_prints_table(tmp_path, capsys):
    out = tmp_path / "demo.json"
    rc = main(
        ["demo", "--places", "80", "--method", "pixels", "--method", "flyhash", "--out", str(out)]
    )
    assert rc == 0
    printed = capsys.readouterr().out
    assert "pixels" in printed and "flyhash" in printed
    data = json.loads(out.read_text())
    assert [r["method"] for r in data["results"]] == ["pixels", "flyhash"]


def test_demo_times_the_steady_state_not_the_first_call(tmp_path, capsys, monkeypatch):
    # A kernel that pays 0.4 s on its first call, as numba's compilation does on a fresh
    # install: with 40 queries it would add 10 ms to each if the first call were timed.
    import time

    from flyvpr.frontends.pixels import PixelsEncoder

    real = PixelsEncoder.score_codes
    calls = []

    def compiling(self, codes):
        if not calls:
            time.sleep(0.4)
        calls.append(len(codes))
        return real(self, codes)

    monkeypatch.setattr(PixelsEncoder, "score_codes", compiling)
    out = tmp_path / "demo.json"
    assert main(["demo", "--places", "40", "--method", "pixels", "--out", str(out)]) == 0
    (result,) = json.loads(out.read_text())["results"]
    assert result["timing"]["per_query_ms"] < 5.0
    assert len(calls) >= 2 and calls[-1] == 40  # the timed call came after the warm-up
    assert "first-call compilation" in capsys.readouterr().out


def test_demo_suggests_commands_a_user_can_run(capsys):
    import shlex

    from flyvpr.cli import build_parser

    assert main(["demo", "--places", "20", "--method", "pixels"]) == 0
    printed = capsys.readouterr().out
    assert "shared/data" not in printed  # only a checkout of this repository has it
    commands = [
        part
        for line in printed.splitlines()
        if line.startswith("  flyvpr ")
        for part in line.strip().split(" && ")
    ]
    assert len(commands) == 3 and "--dataset generic" in commands[0]
    for command in commands:  # each parses with the real CLI
        build_parser().parse_args(shlex.split(command)[1:])


def test_python_m_flyvpr_runs():
    import subprocess
    import sys

    res = subprocess.run(
        [sys.executable, "-m", "flyvpr", "--version"], capture_output=True, text=True, check=False
    )
    assert res.returncode == 0 and "flyvpr" in res.stdout


def test_real_nordland_flynet(nordland_64x32, tmp_path):
    out = tmp_path / "r.json"
    rc = main(
        [
            "evaluate",
            "--dataset",
            "nordland",
            "--root",
            str(nordland_64x32),
            "--reference",
            "summer",
            "--query",
            "winter",
            "--first",
            "0",
            "--count",
            "300",
            "--tolerance",
            "20",
            "--method",
            "flynet",
            "--seed",
            "0",
            "--out",
            str(out),
            "--quiet",
            "--no-cache",
        ]
    )
    assert rc == 0
    data = json.loads(out.read_text())
    assert data["n_query"] == 300 and 0 < data["train_accuracy"] <= 1
    assert np.isfinite(data["auc"])


def test_experiment_and_report_commands(tmp_path, capsys):
    from flyvpr.cli import main

    save_route(make_route(20, random_state=0), tmp_path / "route")
    config = tmp_path / "exp.toml"
    config.write_text(
        "[settings]\ncache = false\n"
        '[[datasets]]\nname = "syn"\nloader = "nordland"\nroot = "route"\n'
        'reference = "summer"\nquery = "winter"\ntolerance = 2\n'
        '[[grids]]\nname = "g"\nkind = "evaluate"\ndatasets = ["syn"]\n'
        'methods = ["pixels", "seqslam"]\n',
        encoding="utf-8",
    )
    out = tmp_path / "out"
    assert main(["experiment", str(config), "--out", str(out), "--jobs", "2", "-q"]) == 0
    assert "2 ran now, 0 failed" in capsys.readouterr().out
    assert main(["experiment", str(config), "--out", str(out), "-q"]) == 0
    assert "2 already finished, 0 ran now" in capsys.readouterr().out
    assert main(["report", str(out)]) == 0
    assert (out / "report.html").is_file() and (out / "report.md").is_file()


def test_experiment_command_errors(tmp_path, capsys):
    from flyvpr.cli import main

    assert main(["experiment", str(tmp_path / "none.toml"), "--out", str(tmp_path)]) == 1
    assert "experiment config not found" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "none")]) == 1
    assert "results folder not found" in capsys.readouterr().err


def test_library_parameters_are_shown_as_options(route_folder, tmp_path, capsys):
    from flyvpr.cli._common import as_options
    from flyvpr.sources import open_source

    src = route_folder(60) / "summer"
    # the library names its parameters ...
    with pytest.raises(
        ValueError, match=r"^every=2m: .* \(positions=CSV or position_topic=TOPIC\)"
    ):
        next(open_source(src).batches((32, 64), every="2m"))
    # ... the command line the options that set them
    code = main(["map", str(src), "--every", "2m", "--out", str(tmp_path / "m.map")])
    err = capsys.readouterr().err
    assert code == 1 and not (tmp_path / "m.map").exists()
    assert "--every 2m: keeping frames by distance needs positions" in err
    assert "(--positions CSV or --position-topic TOPIC)" in err and "every=" not in err
    assert as_options("topic=/a; position_topic=/b; n_every=3; my-topic=4") == (
        "--topic /a; --position-topic /b; n_every=3; my-topic=4"
    )


def test_evaluate_load_names_the_model_and_checks_its_window(route_dir, tmp_path, capsys, caplog):
    model = tmp_path / "m.npz"
    common = [*_eval_args(route_dir)[1:], "--count", "30"]
    fit = ["fit", *[a for a in common if a not in ("--query", "winter", "--tolerance", "2")]]
    assert main([*fit, "--method", "pixels", "--first", "0", "--save", str(model)]) == 0
    capsys.readouterr()
    out = tmp_path / "r.json"
    with caplog.at_level("WARNING", logger="flyvpr"):
        assert (
            main(["evaluate", *common, "--first", "0", "--load", str(model), "--out", str(out)])
            == 0
        )
    assert f"model={model}" in capsys.readouterr().out
    data = json.loads(out.read_text())
    # the seed `flyvpr fit` was given (0 by default) is kept in the file and reported
    assert data["seed"] == 0 and data["model_file"] == str(model)
    assert not [r for r in caplog.records if "find their own place" in r.getMessage()]
    # another window of the route: the model's places are not these frames
    with caplog.at_level("WARNING", logger="flyvpr"):
        assert main(["evaluate", *common, "--first", "30", "--load", str(model)]) == 0
    (warning,) = [r for r in caplog.records if "find their own place" in r.getMessage()]
    assert str(model) in warning.getMessage() and "--first" in warning.getMessage()
    # the seed was the fit's: refused with --load, as --param is
    capsys.readouterr()
    assert main(["evaluate", *common, "--load", str(model), "--seed", "3"]) == 2
    assert "--seed: a model loaded with --load is fitted already" in capsys.readouterr().err


def test_evaluate_load_compares_with_the_models_own_training_accuracy(
    route_dir, tmp_path, capsys, caplog
):
    # FlyNet with 5% winner-take-all fits its own 30 places poorly (training accuracy 27%):
    # fewer than half of its frames (43%) find their own place even on the window it was
    # fitted on, which is no sign of another window (a fixed 50% warned there); on another
    # window none do.
    from flyvpr.datasets import load_benchmark
    from flyvpr.evaluation import self_match_share
    from flyvpr.modelio import load_method

    model = tmp_path / "m.npz"
    common = [*_eval_args(route_dir)[1:], "--count", "30"]
    fit = ["fit", *[a for a in common if a not in ("--query", "winter", "--tolerance", "2")]]
    params = ["--param", "wta_ratio=0.05", "--param", "epochs=40"]
    assert main([*fit, "--method", "flynet", *params, "--first", "0", "--save", str(model)]) == 0
    fitted = load_method(model)
    own = load_benchmark("nordland", root=route_dir, reference="summer", count=30)
    own_share = self_match_share(fitted, own.reference.load_images(cache=False, progress=False))
    assert fitted.train_accuracy / 2 < own_share < 0.5
    capsys.readouterr()
    with caplog.at_level("WARNING", logger="flyvpr"):
        assert main(["evaluate", *common, "--first", "0", "--load", str(model)]) == 0
    assert not [r for r in caplog.records if "find their own place" in r.getMessage()]
    with caplog.at_level("WARNING", logger="flyvpr"):
        assert main(["evaluate", *common, "--first", "30", "--load", str(model)]) == 0
    (warning,) = [r for r in caplog.records if "find their own place" in r.getMessage()]
    assert "its training accuracy on the frames it was fitted on: " in warning.getMessage()


def test_evaluate_load_takes_the_models_image_size(route_dir, tmp_path, capsys):
    model = tmp_path / "k16.npz"
    common = [*_eval_args(route_dir)[1:], "--count", "30"]
    fit = ["fit", *[a for a in common if a not in ("--query", "winter", "--tolerance", "2")]]
    assert main([*fit, "--method", "kenyon", "--size", "16x32", "--save", str(model)]) == 0
    out = tmp_path / "r.json"
    capsys.readouterr()
    assert main(["evaluate", *common, "--load", str(model), "--out", str(out)]) == 0
    assert "size=16x32" in capsys.readouterr().out
    assert json.loads(out.read_text())["image_size"] == [16, 32]
    # a --size that is given must be the model's
    assert main(["evaluate", *common, "--load", str(model), "--size", "32x64"]) == 1
    assert "was fitted on 16x32 images; got size 32x64 (the size to load it at: --size" in (
        capsys.readouterr().err
    )
    # without --load the default stays 32x64
    assert main(["evaluate", *common, "--method", "pixels", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["image_size"] == [32, 64]


@pytest.mark.parametrize(
    ("option", "says", "points_to_experiment"),
    [
        (
            ["--method", "pixels", "--method", "seqslam"],
            "--method given twice (pixels, seqslam)",
            True,
        ),
        (["--method", "pixels", "--seed", "1", "--seed", "2"], "--seed given twice (1, 2)", False),
        (
            ["--method", "seqslam", "--param", "sequence_length=60", "--param",
             "sequence_length=20"],
            "--param sequence_length: given twice (60, 20); one per run",
            False,
        ),
        (
            ["--method", "kenyon+cann", "--param", "jitter=0.1", "--param", "filter.jitter=0.2"],
            "--param jitter: given twice (0.1, 0.2)",
            False,
        ),
    ],
)  # fmt: skip
def test_an_option_given_twice_is_refused(route_dir, capsys, option, says, points_to_experiment):
    assert main(_eval_args(route_dir, *option)) == 2
    err = capsys.readouterr().err
    assert says in err and "one per run" in err
    assert ("flyvpr experiment" in err) == points_to_experiment


@pytest.mark.parametrize(
    ("interrupt", "code", "says"),
    [
        (KeyboardInterrupt(), 130, "flyvpr: interrupted"),
        ("terminated", 143, "terminated by SIGTERM"),
    ],
)
def test_an_interrupt_inside_a_compiled_kernel_exits_as_an_interrupt(
    monkeypatch, capsys, interrupt, code, says
):
    # numba re-raises an exception set during a kernel as SystemError("... returned a result
    # with an exception set"), the interrupt chained to it
    import argparse

    import flyvpr.cli as cli

    if interrupt == "terminated":
        interrupt = cli.Terminated()

    def func(args):
        try:
            raise interrupt
        except BaseException as exc:
            raise SystemError("CPUDispatcher(...) returned a result with an exception set") from exc

    chosen = [func]

    class Parser:
        def parse_args(self, argv):
            return argparse.Namespace(verbose=0, command="map", func=chosen[0])

    monkeypatch.setattr(cli, "build_parser", Parser)
    assert cli.main([]) == code
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err and len(err.strip().splitlines()) == 1

    def other(args):  # a SystemError of another cause is not an interrupt
        raise SystemError("something else")

    chosen[0] = other
    with pytest.raises(SystemError, match="something else"):
        cli.main([])


def test_fit_reads_the_reference_traverse_only(tmp_path, capsys):
    # a generic root with the reference folder alone: the default query folder ("query") is
    # not there, and fit does not need it (it failed: image folder not found)
    from PIL import Image

    from flyvpr.modelio import load_method
    from flyvpr.synthetic import make_route

    route = make_route(12, size=(32, 64), conditions=("summer",), random_state=2)
    folder = tmp_path / "root" / "reference"
    folder.mkdir(parents=True)
    for i, frame in enumerate(route.images["summer"]):
        Image.fromarray(np.rint(frame * 255).astype(np.uint8)).save(folder / f"{i:03d}.png")
    positions = tmp_path / "xy.csv"  # ground truth only: its query rows name other images
    positions.write_text("traverse,filename,x,y\nquery,x.png,0,0\n")
    model = tmp_path / "m.npz"
    argv = ["fit", "--dataset", "generic", "--root", str(tmp_path / "root"),
            "--method", "pixels", "--save", str(model)]  # fmt: skip
    assert main([*argv, "--positions-csv", str(positions), "--radius", "5"]) == 0
    assert "fitted on 12 reference places" in capsys.readouterr().out
    assert load_method(model).frontend.n_reference_ == 12
    # a query that is given must be there
    assert main([*argv, "--query", "winter"]) == 1
    assert "image folder not found" in capsys.readouterr().err


def test_evaluate_says_how_many_queries_have_a_true_match(route_dir, tmp_path, capsys):
    # queries 0-9 of the 60 lie 400 m off (no reference within 5 m): recall counts 50
    root = _route_with_positions(route_dir, tmp_path, offset=3.0)
    csv_path = root / "positions.csv"
    rows = [line.split(",") for line in csv_path.read_text().splitlines()]
    for row in rows:
        if row[0] == "query" and float(row[2]) < 100:  # query frames 0-9: x 3-93
            row[3] = "400"
    csv_path.write_text("\n".join(",".join(row) for row in rows) + "\n")
    assert main(_generic_args(root, 5)) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert "n_query=60 (50 with a true match)" in header
    (tmp_path / "b").mkdir()
    assert main(_generic_args(_route_with_positions(route_dir, tmp_path / "b", 3.0), 5)) == 0
    assert "with a true match" not in capsys.readouterr().out


def test_an_output_into_an_image_folder_of_the_run_is_refused(route_dir, tmp_path, capsys):
    # the next run on that folder would refuse the file: refused before any work
    import shutil

    root = tmp_path / "route"
    shutil.copytree(route_dir, root)
    for out, folder in (
        (root / "winter" / "result.json", root / "winter"),
        (root / "summer" / "sub" / "r.json", root / "summer"),
    ):
        assert main(_eval_args(root, "--method", "pixels", "--out", str(out))) == 2
        assert f"--out {out} would go into {folder}, a folder" in capsys.readouterr().err
        assert not out.exists() and not (root / "summer" / "sub").exists()
    assert main(["map", str(root / "summer"), "--out", str(root / "summer" / "r.map")]) == 2
    assert "a folder of images this run reads" in capsys.readouterr().err
    assert main(_eval_args(root, "--method", "pixels", "--out", str(root / "r.json"))) == 0
