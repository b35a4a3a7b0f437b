"""Experiment configs (parsing, validation, grid expansion) and the resumable runner."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from flyvpr.cli import main
from flyvpr.experiments import load_config, parse_config, run_experiment
from flyvpr.experiments.config import KINDS, run_id_of
from flyvpr.methods import METHODS, make_method

REPO = Path(__file__).resolve().parents[1]
N_PLACES = 30

BASE = """
[settings]
cache = "cache"

[[datasets]]
name = "syn"
loader = "nordland"
root = "route"
reference = "summer"
query = "winter"
tolerance = 2
"""


@pytest.fixture(scope="module")
def route_dir(route_folder) -> Path:
    return route_folder(N_PLACES)


def write_config(folder: Path, grids: str, base: str = BASE) -> Path:
    path = folder / "config.toml"
    path.write_text(textwrap.dedent(base) + textwrap.dedent(grids), encoding="utf-8")
    return path


@pytest.fixture
def workdir(tmp_path, route_dir) -> Path:
    """A folder holding the route (as a symlink) for configs to refer to as "route"."""
    (tmp_path / "route").symlink_to(route_dir, target_is_directory=True)
    return tmp_path


EVAL_GRID = """
[[grids]]
name = "eval"
kind = "evaluate"
datasets = ["syn"]
methods = ["pixels", "flynet", "seqslam"]
seeds = [0, 1]
method_params = { flynet = { epochs = 5 } }
"""


# -- parsing -------------------------------------------------------------------------------------
def test_parse_expands_the_cartesian_product(tmp_path):
    grids = """
    [[grids]]
    name = "g"
    kind = "evaluate"
    datasets = ["syn"]
    methods = ["flynet", "flyhash"]
    seeds = [0, 1, 2]
    params = { sampling_ratio = [0.1, 0.2], wta_ratio = [0.25, 0.5, 0.75], n_hidden = 32 }
    """
    config = load_config(write_config(tmp_path, grids))
    runs = config.grid_runs(config.grid("g"))
    assert len(runs) == 1 * 2 * 3 * 2 * 3
    assert len({r.run_id for r in runs}) == len(runs)
    assert all(r.spec["frontend_params"]["n_hidden"] == 32 for r in runs)
    assert config.grid("g").axes == ["sampling_ratio", "wta_ratio"]


def test_relative_paths_resolve_against_the_config_folder(tmp_path):
    config = load_config(write_config(tmp_path, EVAL_GRID))
    ds = config.datasets["syn"]
    assert ds.options["root"] == "route"  # as written: part of the run identity
    assert Path(ds.resolved["root"]) == (tmp_path / "route").resolve()
    assert Path(config.settings.cache) == (tmp_path / "cache").resolve()


def test_runs_shared_by_grids_run_once_and_defaults_do_not_change_identity(tmp_path):
    grids = (
        EVAL_GRID
        + """
    [[grids]]
    name = "fp"
    kind = "footprint"
    datasets = ["syn"]
    methods = ["flynet"]
    seeds = [0]
    method_params = { flynet = { epochs = 5, sampling_ratio = 0.1 } }
    """
    )
    config = load_config(write_config(tmp_path, grids))
    eval_ids = {r.run_id for r in config.grid_runs(config.grid("eval"))}
    fp_ids = {r.run_id for r in config.grid_runs(config.grid("fp"))}
    assert fp_ids <= eval_ids  # sampling_ratio=0.1 is FlyNet's default
    assert len(config.runs()) == len(eval_ids)


def test_run_id_is_stable_and_readable(tmp_path):
    config = load_config(write_config(tmp_path, EVAL_GRID))
    run = config.runs()[0]
    again = load_config(write_config(tmp_path, EVAL_GRID)).runs()[0]
    assert run.run_id == again.run_id == run_id_of(run.spec)
    assert run.run_id.startswith("evaluate-syn-pixels-s0-")
    changed = dict(run.spec, seed=5)
    assert run_id_of(changed) != run.run_id


def test_a_whole_number_names_one_run_whether_written_as_int_or_float(tmp_path):
    # cann's speed_prior and adaptation default to 1.0 and 50.0, seqslam's enhance_window to 10
    def runs(method_params=None):
        text = grid(methods='["kenyon+cann", "seqslam"]', method_params=method_params)
        return {r.spec["method"]: r for r in load_config(write_config(tmp_path, text)).runs()}

    default = runs()
    spelled = runs(
        '{ "kenyon+cann" = { speed_prior = 1, adaptation = 50 }, '
        "seqslam = { enhance_window = 10.0, v_max = 1.2 } }"
    )
    assert {m: r.run_id for m, r in spelled.items()} == {m: r.run_id for m, r in default.items()}
    # only the identity is normalised: the method receives the values as written
    filt = spelled["kenyon+cann"].spec["filter_params"]
    assert filt["speed_prior"] == 1 and type(filt["speed_prior"]) is int
    assert type(spelled["seqslam"].spec["filter_params"]["enhance_window"]) is float
    # a boolean is not a number: fallback = 1 is not the default true
    other = runs('{ "kenyon+cann" = { fallback = 1 } }')
    assert other["kenyon+cann"].run_id != default["kenyon+cann"].run_id
    assert other["seqslam"].run_id == default["seqslam"].run_id
    # and a value that differs still makes a new run
    assert runs("{ seqslam = { v_max = 2 } }")["seqslam"].run_id != default["seqslam"].run_id


def test_parameters_route_to_front_end_and_filter(tmp_path):
    grids = """
    [[grids]]
    name = "g"
    kind = "evaluate"
    datasets = ["syn"]
    methods = ["flynet+seqslam"]
    params = { epochs = 3, sequence_length = [5, 10], "filter.v_max" = 1.5 }
    """
    config = load_config(write_config(tmp_path, grids))
    runs = config.runs()
    assert [r.spec["filter_params"]["sequence_length"] for r in runs] == [5, 10]
    assert all(r.spec["frontend_params"]["epochs"] == 3 for r in runs)
    assert all(r.spec["filter_params"]["v_max"] == 1.5 for r in runs)


def test_a_param_both_parts_take_needs_its_prefix(tmp_path):
    # flynet+rnn: FlyNet and the RNN both take epochs; unprefixed, it went to FlyNet only
    grids = """
    [[grids]]
    name = "g"
    kind = "evaluate"
    datasets = ["syn"]
    methods = ["flynet+rnn"]
    params = { epochs = 3 }
    """
    with pytest.raises(
        ValueError,
        match=r"'epochs' is a parameter of both parts of method 'flynet\+rnn' .*"
        r"write 'frontend\.epochs' or 'filter\.epochs'",
    ):
        load_config(write_config(tmp_path, grids))
    prefixed = grids.replace("epochs = 3", '"frontend.epochs" = 3, "filter.epochs" = 2')
    (run,) = load_config(write_config(tmp_path, prefixed)).runs()
    assert run.spec["frontend_params"]["epochs"] == 3
    assert run.spec["filter_params"]["epochs"] == 2


def test_method_seeds_override_the_grid_seeds(tmp_path):
    grids = EVAL_GRID.replace("seeds = [0, 1]", "seeds = [0, 1]\nmethod_seeds = { pixels = [7] }")
    config = load_config(write_config(tmp_path, grids))
    seeds = [(r.spec["method"], r.spec["seed"]) for r in config.runs()]
    assert ("pixels", 7) in seeds and ("pixels", 0) not in seeds
    assert len(seeds) == 1 + 2 + 2


def grid(**overrides) -> str:
    keys = {
        "name": '"g"',
        "kind": '"evaluate"',
        "datasets": '["syn"]',
        "methods": '["flynet"]',
    }
    keys.update(overrides)
    return "[[grids]]\n" + "\n".join(f"{k} = {v}" for k, v in keys.items() if v is not None)


@pytest.mark.parametrize(
    "grids, error, match",
    [
        (
            grid(methods='["flynet", "nope"]'),
            ValueError,
            r'methods must be a non-empty list of distinct method names; got \["flynet", "nope"\]: '
            r'item 2, "nope", is not a method name; known methods: .*flynet',
        ),
        (
            grid(datasets='["other"]'),
            ValueError,
            r'"other", is not a dataset name; known datasets: syn',
        ),
        (grid(datasets='"syn"'), TypeError, r"datasets must be a non-empty list .*\(string\)"),
        (
            grid(kind='"plot"'),
            ValueError,
            r"kind must be one of .*'training_curve'.*; got \"plot\"",
        ),
        (
            grid(seeds='"0"'),
            TypeError,
            r'seeds must be a non-empty list of distinct integers >= 0; got "0" \(string\)',
        ),
        (grid(seeds="[0, 0]"), ValueError, r"seeds must be .*; got \[0, 0\]: it holds 0 twice"),
        (grid(seeds="[0, -1]"), ValueError, r"item 2, -1, is not an integer >= 0"),
        (grid(methods="[]"), ValueError, r"methods must be a non-empty list .*; got \[\]"),
        (
            grid(kind='"training_curve"', methods='["flynet", "pixels", "kenyon+cann"]'),
            ValueError,
            r"\[\[grids\]\] #1 \('g'\): a training_curve grid needs methods whose front end is "
            r"trained epoch by epoch; 'pixels', 'kenyon\+cann' records no per-epoch",
        ),
        (grid(methods=None), ValueError, r"missing required key 'methods': a non-empty list"),
        (grid(params="{ epochs = [] }"), ValueError, r"params\.epochs must be .*; got \[\]"),
        (grid(params="{ nonsense = 1 }"), ValueError, r"'nonsense' is not a parameter of method"),
        (grid(params="{ random_state = 1 }"), ValueError, r"random_state through 'seeds'"),
        (grid(params="3"), TypeError, r"params must be a table of PARAMETER = .*\(integer\)"),
        (
            grid(method_params="{ flynet = 3 }"),
            TypeError,
            r"method_params\.flynet must be a table of PARAMETER = a value; got 3 \(integer\)",
        ),
        (
            grid(method_seeds='{ flynet = ["a"] }'),
            TypeError,
            r"method_seeds\.flynet must be a non-empty list of distinct integers >= 0",
        ),
        (grid(colour='"red"'), ValueError, r"unknown key\(s\) 'colour'; allowed: name, kind"),
        (grid(name='"a b"'), ValueError, r'name must be a name of letters.*; got "a b"'),
        (grid(title="3"), TypeError, r"title must be a string; got 3 \(integer\)"),
        (grid(kind='"sensitivity"'), ValueError, r"exactly one params axis"),
        (grid(examples="3"), ValueError, r"examples applies to kind 'qualitative' only"),
        (grid(warmup="false"), ValueError, r"warmup applies to kind 'timing' only"),
        (
            grid(kind='"qualitative"', examples="0"),
            ValueError,
            r"examples must be an integer >= 1; got 0",
        ),
        (grid(speed="-1"), ValueError, r"speed must be a number > 0 or .*; got -1"),
        (
            grid(speed="[2, 1]"),
            ValueError,
            r"speed must be .*the first <= the second; got \[2, 1\]",
        ),
        (grid(speed='"fast"'), TypeError, r"speed must be a number > 0 .*\(string\)"),
        (grid(speed="nan"), ValueError, r"speed must be a number > 0"),
        (grid(method_params="{ pixels = {} }"), ValueError, r"not in this grid's methods"),
        (grid() + "\n" + grid(), ValueError, r"\[\[grids\]\] name 'g' is used by two blocks"),
        ("", ValueError, r"missing required key 'grids': one or more \[\[grids\]\] blocks"),
        ("[grids]\nname = 1", TypeError, r"grids must be one or more \[\[grids\]\] blocks"),
        (grid() + "\nwhat = ", ValueError, r"not valid TOML"),
    ],
)
def test_invalid_grids_raise_clear_errors(tmp_path, grids, error, match):
    with pytest.raises(error, match=match) as info:
        load_config(write_config(tmp_path, grids))
    assert str(tmp_path / "config.toml") in str(info.value)  # every message names the file
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "top, error, match",
    [
        ('colour = "red"', ValueError, r"^<config>: unknown key\(s\) 'colour'; allowed: title"),
        ("title = 3", TypeError, r"^<config>: title must be a string; got 3 \(integer\)"),
        ("settings = 3", TypeError, r"settings must be a \[settings\] table; got 3"),
    ],
)
def test_invalid_top_level_keys(tmp_path, top, error, match):
    datasets = BASE.replace('[settings]\ncache = "cache"\n', "")
    with pytest.raises(error, match=match):
        parse_config(top + "\n" + datasets + grid(), base_dir=tmp_path)


def test_unknown_method_lists_the_known_ones(tmp_path):
    with pytest.raises(ValueError) as info:
        load_config(write_config(tmp_path, grid(methods='["flynett"]')))
    message = str(info.value)
    assert "config.toml" in message and "'g'" in message
    assert all(name in message for name in METHODS)


@pytest.mark.parametrize(
    "dataset, error, match",
    [
        (
            'name = "d"\nloader = "kitti"\nroot = "x"',
            ValueError,
            r"\('d'\): loader must be one of .*'nordland'.*; got \"kitti\"",
        ),
        (
            'name = "d"\nloader = "nordland"\nroot = "x"\nradius = 3',
            ValueError,
            r"loader 'nordland' takes no option\(s\) 'radius'; its options: root, reference",
        ),
        (
            'name = "d"\nloader = "nordland"\nroot = "x"\ncount = "10"',
            TypeError,
            r'count must be an integer >= 1; got "10" \(string\)',
        ),
        (
            'name = "d"\nloader = "nordland"\nroot = "x"\nfirst = true',
            TypeError,
            r"first must be an integer >= 0; got true \(boolean\)",
        ),
        (
            'name = "d"\nloader = "robotcar"\nroot = "x"\nspacing = 0',
            ValueError,
            r"spacing must be a number > 0; got 0",
        ),
        (
            'name = "d"\nloader = "robotcar"\nroot = "x"',
            ValueError,
            r"\('d'\): loader 'robotcar': 'reference' is required for this dataset",
        ),
        (
            'name = "d"\nloader = "robotcar"\nroot = "x"\nreference = "a"',
            ValueError,
            r"\('d'\): loader 'robotcar': 'query' is required for this dataset",
        ),
        ('name = "d"\nloader = "nordland"', ValueError, r"missing required key 'root': a path"),
        ('loader = "nordland"\nroot = "x"', ValueError, r"#2: missing required key 'name'"),
        (
            'name = "syn"\nloader = "nordland"\nroot = "x"',
            ValueError,
            r"\[\[datasets\]\] name 'syn' is used by two",
        ),
    ],
)
def test_invalid_dataset_blocks_raise_clear_errors(tmp_path, dataset, error, match):
    text = BASE + "\n[[datasets]]\n" + dataset + "\n" + grid()
    with pytest.raises(error, match=match):
        parse_config(text, base_dir=tmp_path)


@pytest.mark.parametrize(
    "settings, error, match",
    [
        ("image_size = [32]", ValueError, r"image_size must be a list of 2 integers >= 1"),
        ("image_size = [32, 0]", ValueError, r"item 2, 0, is not an integer >= 1"),
        ("cache = 3", TypeError, r"cache must be true or false or a path"),
        ("jobs = 3", ValueError, r"unknown key\(s\) 'jobs'"),
    ],
)
def test_invalid_settings(tmp_path, settings, error, match):
    text = BASE.replace('cache = "cache"', settings) + grid()
    with pytest.raises(error, match=match):
        parse_config(text, base_dir=tmp_path)


def test_a_cache_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "cache").write_text("not a folder")
    with pytest.raises(ValueError, match=r"config.toml \[settings\]: cache '.*cache' is a file"):
        load_config(write_config(tmp_path, EVAL_GRID))
    (tmp_path / "cache").unlink()
    (tmp_path / "cache").mkdir()
    assert load_config(write_config(tmp_path, EVAL_GRID)).settings.cache == str(tmp_path / "cache")


def test_missing_config_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.toml"):
        load_config(tmp_path / "nothere.toml")


# -- running -------------------------------------------------------------------------------------
def run_files(out: Path) -> dict[str, Path]:
    return {p.stem: p for p in (out / "runs").glob("*.json")}


def test_run_experiment_in_parallel_and_resume(workdir):
    config = write_config(workdir, EVAL_GRID)
    out = workdir / "out"
    first = run_experiment(config, out, n_jobs=2, backend="loky", progress=False)
    assert first["n_runs"] == 6 and first["n_skipped"] == 0 and not first["errors"]
    files = run_files(out)
    assert sorted(files) == sorted(first["ran"])
    assert not list((out / "runs").glob(".*"))  # no temporary files left behind
    record = json.loads(files[first["ran"][0]].read_text())
    assert record["status"] == "ok"
    assert len(record["predictions"]) == len(record["correct"]) == N_PLACES
    assert record["protocol"]["tolerance"] == {"frames": 2}
    assert record["machine"]["cores"] >= 1

    # an interruption: one run's file is gone; only that run is redone
    victim = sorted(files)[2]
    files[victim].unlink()
    mtimes = {k: p.stat().st_mtime_ns for k, p in run_files(out).items()}
    second = run_experiment(config, out, n_jobs=2, progress=False)
    assert second["ran"] == [victim] and second["n_skipped"] == 5
    assert {k: p.stat().st_mtime_ns for k, p in run_files(out).items() if k != victim} == mtimes
    experiment = json.loads((out / "experiment.json").read_text())
    assert len(experiment["sessions"]) == 2
    assert experiment["sessions"][-1]["n_ran"] == 1


def test_a_failing_run_is_recorded_and_retried(workdir):
    # a value the config cannot check (the front end checks it when it fits) fails the run
    grids = """
    [[grids]]
    name = "curves"
    kind = "training_curve"
    datasets = ["syn"]
    methods = ["flynet", "flynet+cann"]
    method_params = { flynet = { epochs = 4 }, "flynet+cann" = { epochs = 2, n_hidden = 0 } }
    """
    config = write_config(workdir, grids)
    out = workdir / "out"
    summary = run_experiment(config, out, n_jobs=1, progress=False)
    assert len(summary["ran"]) == 2
    (failed,) = summary["errors"]
    assert "n_hidden must be >= 1" in summary["errors"][failed]
    record = json.loads((out / "runs" / f"{failed}.json").read_text())
    assert record["status"] == "error" and "Traceback" in record["traceback"]
    ok = json.loads(next(p for k, p in run_files(out).items() if k != failed).read_text())
    assert ok["status"] == "ok" and len(ok["result"]["accuracy_history"]) == 4
    again = run_experiment(config, out, n_jobs=1, progress=False)
    assert again["ran"] == [failed]  # errors are retried, finished runs are not


def test_timing_runs_decode_without_cache(workdir):
    grids = """
    [[grids]]
    name = "t"
    kind = "timing"
    datasets = ["syn"]
    methods = ["seqslam"]
    """
    out = workdir / "out"
    summary = run_experiment(write_config(workdir, grids), out, progress=False)
    record = json.loads(run_files(out)[summary["ran"][0]].read_text())
    timing = record["result"]["timing"]
    assert timing["cached"] is False
    assert timing["load_query_s"] > 0 and timing["encode_s"] >= 0


def test_speed_profile_subsets_the_queries(workdir):
    grids = EVAL_GRID.replace("seeds = [0, 1]", "seeds = [0]\nspeed = 2.0")
    out = workdir / "out"
    summary = run_experiment(write_config(workdir, grids), out, progress=False)
    record = json.loads(run_files(out)[summary["ran"][0]].read_text())
    assert len(record["predictions"]) == N_PLACES // 2
    assert record["protocol"]["speed"] == 2.0


GENERIC = """
[settings]
cache = "cache"

[[datasets]]
name = "syn"
loader = "generic"
root = "route"
reference = "summer"
query = "winter"
tolerance = 2
"""

QUICK_GRID = """
[[grids]]
name = "eval"
kind = "evaluate"
datasets = ["syn"]
methods = ["pixels", "seqslam"]
"""


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_run_whose_data_changed_since_runs_again(tmp_path, route_dir, caplog):
    import shutil

    shutil.copytree(route_dir, tmp_path / "route")
    config, out = write_config(tmp_path, QUICK_GRID, GENERIC), tmp_path / "out"
    first = run_experiment(config, out, progress=False)
    assert len(first["ran"]) == 2
    record = json.loads(run_files(out)[first["ran"][0]].read_text())
    assert record["data_fingerprint"]["query"]["n_images"] == N_PLACES
    with caplog.at_level(logging.WARNING, logger="flyvpr.experiments"):
        assert run_experiment(config, out, progress=False)["ran"] == []
    assert _warnings(caplog) == []

    # five query frames deleted: the runs are done again, for the data as they are now
    for path in sorted((tmp_path / "route" / "winter").iterdir())[-5:]:
        path.unlink()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="flyvpr.experiments"):
        again = run_experiment(config, out, progress=False)
    assert sorted(again["ran"]) == sorted(first["ran"]) and again["n_skipped"] == 0
    assert _warnings(caplog) == [
        f"dataset 'syn': data changed since the run: query: {N_PLACES - 5} images, were "
        f"{N_PLACES}; running 2 finished runs again"
    ]
    record = json.loads(run_files(out)[first["ran"][0]].read_text())
    assert record["protocol"]["n_query"] == len(record["predictions"]) == N_PLACES - 5

    # a picture rewritten in place (same name, new modification time)
    picture = sorted((tmp_path / "route" / "summer").iterdir())[3]
    os.utime(picture, (1e9, 1e9))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="flyvpr.experiments"):
        assert len(run_experiment(config, out, progress=False)["ran"]) == 2
    (message,) = _warnings(caplog)
    assert "data changed since the run: reference: other image files, sizes or modific" in message

    # a run file of an older flyvpr, without a fingerprint: run again, not trusted
    victim = run_files(out)[first["ran"][1]]
    _drop_key(victim, "data_fingerprint")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="flyvpr.experiments"):
        assert run_experiment(config, out, progress=False)["ran"] == [victim.stem]
    assert _warnings(caplog) == [
        "dataset 'syn': the files of 1 finished run, written by an older flyvpr, record no "
        "fingerprint of their data, which may have changed since; running them again"
    ]
    assert "data_fingerprint" in json.loads(victim.read_text())


def test_the_data_are_fingerprinted_once_per_dataset_and_invocation(workdir, monkeypatch):
    from flyvpr.datasets import Benchmark

    calls = []
    real = Benchmark.fingerprint
    monkeypatch.setattr(Benchmark, "fingerprint", lambda self: calls.append(1) or real(self))
    grids = EVAL_GRID.replace("seeds = [0, 1]", "seeds = [0, 1]\nspeed = 2.0")
    config, out = write_config(workdir, grids), workdir / "out"
    assert len(run_experiment(config, out, n_jobs=1, progress=False)["ran"]) == 6
    assert len(calls) == 1
    assert run_experiment(config, out, n_jobs=1, progress=False)["n_skipped"] == 6
    assert len(calls) == 2


def _positions_csv(root: Path, offset: float) -> Path:
    """Reference frame i at (10 i, 0), query frame i at (10 i + offset, 0)."""
    lines = ["traverse,filename,x,y"]
    for role, folder, shift in (("reference", "summer", 0.0), ("query", "winter", offset)):
        for i, path in enumerate(sorted((root / folder).iterdir())):
            lines.append(f"{role},{path.name},{10 * i + shift},0")
    path = root / "positions.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_a_ground_truth_without_a_true_match_is_refused_before_any_run(
    tmp_path, route_dir, monkeypatch
):
    import shutil

    from flyvpr.experiments import runner

    shutil.copytree(route_dir, tmp_path / "route")
    _positions_csv(tmp_path / "route", offset=3.0)
    base = GENERIC.replace("tolerance = 2", 'positions_csv = "route/positions.csv"\nradius = 1')
    config, out = write_config(tmp_path, QUICK_GRID, base), tmp_path / "out"
    monkeypatch.setattr(runner, "execute_run", lambda run: pytest.fail("a run started"))
    with pytest.raises(ValueError) as info:
        run_experiment(config, out, progress=False)
    assert str(info.value) == (
        f"{config} [[datasets]] #1 ('syn'): the ground truth gives no query a true match: none "
        f"of the {N_PLACES} queries lies within the tolerance (1.0 metres) of any of the "
        f"{N_PLACES} references, so recall is undefined; widen the tolerance (or radius), or "
        "check the frames (or positions) of the two traverses"
    )
    assert not out.exists()
    # a training curve needs no ground truth: it runs
    curves = QUICK_GRID.replace('"evaluate"', '"training_curve"').replace(
        '["pixels", "seqslam"]', '["flynet"]\nparams = { epochs = 2 }'
    )
    monkeypatch.undo()
    summary = run_experiment(write_config(tmp_path, curves, base), out, progress=False)
    assert len(summary["ran"]) == 1 and not summary["errors"]


def test_missing_data_fails_before_any_run(tmp_path):
    out = tmp_path / "out"
    config = write_config(tmp_path, EVAL_GRID)
    with pytest.raises(FileNotFoundError, match="route") as info:
        run_experiment(config, out, progress=False)
    # the message names the config's file and block; nothing is written
    assert str(info.value).startswith(f"{config} [[datasets]] #1 ('syn'): ")
    assert not out.exists()


def test_data_that_fails_leaves_a_results_folder_as_it_was(workdir):
    out = workdir / "out"
    grids = EVAL_GRID.replace('methods = ["pixels", "flynet", "seqslam"]', 'methods = ["pixels"]')
    grids = grids.replace("method_params = { flynet = { epochs = 5 } }\n", "")
    run_experiment(write_config(workdir, grids), out, progress=False)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    broken = write_config(workdir, grids, BASE.replace('root = "route"', 'root = "nope"'))
    with pytest.raises(FileNotFoundError, match=r"\[\[datasets\]\] #1 \('syn'\): .*nope"):
        run_experiment(broken, out, progress=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # a window beyond the data is named the same way (a ValueError from the loader)
    beyond = write_config(workdir, grids, BASE + "first = 25\ncount = 50\n")
    with pytest.raises(ValueError, match=r"\[\[datasets\]\] #1 \('syn'\): .*beyond"):
        run_experiment(beyond, out, progress=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_qualitative_queries_beyond_the_data_are_refused(workdir):
    grids = """
    [[grids]]
    name = "shown"
    kind = "qualitative"
    datasets = ["syn"]
    methods = ["pixels"]
    queries = [5, 5000, 29]
    """
    out = workdir / "out"
    with pytest.raises(ValueError) as info:
        run_experiment(write_config(workdir, grids), out, progress=False)
    assert str(info.value) == (
        f"{workdir / 'config.toml'} [[grids]] 'shown': queries 5000 lie beyond the "
        f"{N_PLACES} queries of dataset 'syn' (positions 0-{N_PLACES - 1})"
    )
    assert not out.exists()
    ok = grids.replace("5000, ", "")
    assert run_experiment(write_config(workdir, ok), out, progress=False)["errors"] == {}


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"n_jobs": 0}, ValueError, "n_jobs must be a non-zero int"),
        ({"n_jobs": 1.5}, TypeError, "n_jobs must be an int"),
        ({"backend": "spark"}, ValueError, "backend must be one of .*dask"),
    ],
)
def test_bad_runner_arguments(tmp_path, kwargs, error, match):
    with pytest.raises(error, match=match):
        run_experiment(write_config(tmp_path, EVAL_GRID), tmp_path / "out", **kwargs)


@pytest.mark.parametrize("backend, module", [("dask", "distributed"), ("ray", "ray")])
def test_cluster_backends_name_their_install(workdir, backend, module):
    import importlib.util

    if importlib.util.find_spec(module) is not None:
        pytest.skip(f"{module} is installed")
    with pytest.raises(ImportError, match=f"backend '{backend}' needs"):
        run_experiment(
            write_config(workdir, EVAL_GRID), workdir / "out", backend=backend, progress=False
        )


def test_importing_experiments_loads_neither_matplotlib_nor_torch():
    code = (
        "import sys, flyvpr.experiments; print('matplotlib' in sys.modules, 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


# -- the paper's config --------------------------------------------------------------------------
def test_paper_config(shared_data):
    path = REPO / "experiments" / "paper.toml"
    text = path.read_text(encoding="utf-8")
    import tomllib

    wanted = {m for g in tomllib.loads(text)["grids"] for m in g["methods"]}
    missing = sorted(wanted - set(METHODS))
    if missing:
        message = f"methods not registered yet: {missing}"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    config = load_config(path)
    assert {g.kind for g in config.grids} == set(KINDS)
    for ds in config.datasets.values():
        root = Path(ds.resolved["root"])
        assert root.is_dir(), f"{ds.name}: {root}"
        assert root.resolve().parent == shared_data.resolve()
    # the footprint and qualitative grids add no runs of their own
    base = {
        r.run_id
        for g in config.grids
        if g.kind != "footprint" and g.kind != "qualitative"
        for r in config.grid_runs(g)
    }
    assert {r.run_id for r in config.runs()} == base


# -- faults: files that are not what they should be, signals --------------------------------------
def test_config_with_a_latin1_byte_names_the_file_and_line(tmp_path, capsys):
    path = write_config(tmp_path, EVAL_GRID)
    data = path.read_bytes().replace(b'name = "eval"', b'name = "eval"\ntitle = "caf\xe9"')
    path.write_bytes(data)
    line = data[: data.index(b"\xe9")].count(b"\n") + 1
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: line {line}: not UTF-8"):
        load_config(path)
    assert main(["experiment", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and f"line {line}" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda p: p.write_text(p.read_text()[:100]), r"not valid JSON .*truncated or garbled"),
        (lambda p: p.write_bytes(b""), r"not valid JSON .*truncated or garbled"),
        (lambda p: p.write_bytes(b"\xff\xfe" + p.read_bytes()), r"not UTF-8 text"),
    ],
    ids=["truncated", "empty", "latin1"],
)
def test_an_unparsable_run_file_is_run_again_with_one_warning(
    workdir, capsys, caplog, damage, reason
):
    # A file cut short (a copy that stopped, a full disk) holds no run: that run is not done.
    config = write_config(workdir, EVAL_GRID.replace("seeds = [0, 1]", "seeds = [0]"))
    out = workdir / "out"
    run_experiment(config, out, progress=False)
    files = run_files(out)
    victim = sorted(files.values())[0]
    damage(victim)
    others = {p: p.read_bytes() for p in files.values() if p != victim}
    with caplog.at_level(logging.WARNING, logger="flyvpr.experiments"):
        assert main(["experiment", str(config), "--out", str(out), "--quiet"]) == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert re.search(rf"^{re.escape(str(victim))}: .*{reason}.*; running it again$", warnings[0])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert f"{len(files) - 1} already finished, 1 ran now, 0 failed" in captured.out
    assert json.loads(victim.read_text())["status"] == "ok"  # redone and rewritten whole
    assert {p: p.read_bytes() for p in others} == others  # the finished runs are untouched


@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda p: _drop_key(p, "result"), r"with key 'result' \(a finished evaluate run\)"),
        (lambda p: _drop_key(p, "status"), r"with key 'status'"),
        (lambda p: p.write_text("[1, 2]"), r"a JSON object\); got a list"),
    ],
    ids=["no-result", "no-status", "a-list"],
)
def test_a_run_file_of_another_shape_stops_a_resumed_experiment(workdir, capsys, damage, match):
    config = write_config(workdir, EVAL_GRID.replace("seeds = [0, 1]", "seeds = [0]"))
    out = workdir / "out"
    run_experiment(config, out, progress=False)
    victim = sorted(run_files(out).values())[0]
    damage(victim)
    before = {p: p.read_bytes() for p in run_files(out).values()}
    with pytest.raises(ValueError, match=match) as info:
        run_experiment(config, out, progress=False)
    assert str(info.value).startswith(f"{victim}: ")
    assert {p: p.read_bytes() for p in run_files(out).values()} == before  # nothing rewritten
    assert main(["experiment", str(config), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(victim) in err and "Traceback" not in err


def _drop_key(path: Path, key: str) -> None:
    record = json.loads(path.read_text())
    del record[key]
    path.write_text(json.dumps(record))


@pytest.mark.parametrize("content", ["{}", '{"sessions": 3}', "nonsense"])
def test_an_experiment_json_of_something_else_is_refused(workdir, content):
    out = workdir / "out"
    out.mkdir()
    (out / "experiment.json").write_text(content)
    with pytest.raises(ValueError, match=r"experiment.json: expected the record of `flyvpr exp"):
        run_experiment(write_config(workdir, EVAL_GRID), out, progress=False)
    assert (out / "experiment.json").read_text() == content
    assert not run_files(out)


def _descendants(pid: int) -> set[int]:
    """Process ids below ``pid`` (Linux /proc)."""
    found, todo = set(), [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                children = (task / "children").read_text().split()
            except OSError:
                continue
            for child in map(int, children):
                if child not in found:
                    found.add(child)
                    todo.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("entry", ["cli", "library"])
def test_sigterm_takes_the_worker_processes_down(workdir, entry):
    grid = EVAL_GRID.replace('"pixels", "flynet", "seqslam"', '"flynet"').replace(
        "epochs = 5", "epochs = 10000000"
    )
    config, out = write_config(workdir, grid), workdir / "out"
    if entry == "cli":
        code = "from flyvpr.cli import main; import sys; sys.exit(main(sys.argv[1:]))"
    else:
        code = (
            "import sys; from flyvpr.experiments import run_experiment; "
            "run_experiment(sys.argv[2], sys.argv[4], n_jobs=2, progress=False)"
        )
    args = ["experiment", str(config), "--out", str(out), "--jobs", "2", "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.Popen([sys.executable, "-c", code, *args], env=env, stderr=subprocess.PIPE)
    workers: set[int] = set()
    deadline = time.monotonic() + 120
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
        workers = {p for p in _descendants(proc.pid) if "Loky" in _cmdline(p)}
    assert len(workers) >= 2, "the two workers never started"
    time.sleep(1.0)  # the workers are in the middle of their runs (100000 epochs)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    deadline = time.monotonic() + 10
    while any(map(_alive, workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(map(_alive, workers)), "worker processes outlived the experiment"
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    assert not run_files(out)
    assert b"Traceback" not in err


def test_worker_processes_leave_ctrl_c_to_the_calling_process(workdir, monkeypatch):
    # Ctrl-C signals the whole process group: a worker between two runs printed its own
    # KeyboardInterrupt traceback, while the calling process stops the workers anyway
    from flyvpr.experiments import runner

    real = runner.execute_run

    def execute_and_look(run):  # (a local function: sent to the workers by value)
        return {**real(run), "sigint": str(signal.getsignal(signal.SIGINT))}

    monkeypatch.setattr(runner, "execute_run", execute_and_look)
    grids = QUICK_GRID.replace('"seqslam"]', '"seqslam"]\nseeds = [0, 1]')
    config, out = write_config(workdir, grids), workdir / "out"
    before = signal.getsignal(signal.SIGINT)  # (SIG_IGN where the tests run in the background)
    assert len(run_experiment(config, out, n_jobs=2, progress=False)["ran"]) == 4
    handlers = {json.loads(p.read_text())["sigint"] for p in run_files(out).values()}
    assert handlers == {str(signal.SIG_IGN)}
    assert signal.getsignal(signal.SIGINT) is before  # not here


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_ctrl_c_stops_the_workers_without_their_tracebacks(workdir):
    # Ctrl-C (or `timeout -s INT`) signals the whole process group, the workers included
    grid = EVAL_GRID.replace('"pixels", "flynet", "seqslam"', '"flynet"').replace(
        "epochs = 5", "epochs = 10000000"
    )
    config, out = write_config(workdir, grid), workdir / "out"
    code = "from flyvpr.cli import main; import sys; sys.exit(main(sys.argv[1:]))"
    args = ["experiment", str(config), "--out", str(out), "--jobs", "2", "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        env=env,
        stderr=subprocess.PIPE,
        start_new_session=True,
        # (a shell starts a background job with SIGINT ignored, and its children inherit that:
        # the experiment gets Python's own KeyboardInterrupt, as from a terminal)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        workers: set[int] = set()
        deadline = time.monotonic() + 120
        while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
            workers = {p for p in _descendants(proc.pid) if "Loky" in _cmdline(p)}
        assert len(workers) >= 2, "the two workers never started"
        # (a worker still starting up, before it set SIGINT aside, could yet print a traceback)
        deadline = time.monotonic() + 60
        while not all(map(_ignores_sigint, workers)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert all(map(_ignores_sigint, workers)), "the workers do not leave SIGINT to the parent"
        time.sleep(1.0)  # the workers are in the middle of their runs (100000 epochs)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:  # (a failed check: the experiment must not run on)
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    text = err.decode()
    # one line, and no worker's traceback (loky's resource tracker, a process of its own, may
    # yet warn of a semaphore it cleans up at shutdown)
    assert text.startswith("flyvpr: interrupted\n")
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
    deadline = time.monotonic() + 10
    while any(map(_alive, workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(map(_alive, workers)), "worker processes outlived the experiment"


def _ignores_sigint(pid: int) -> bool:
    """Whether process ``pid`` ignores SIGINT (Linux /proc: the SigIgn mask)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(line.split()[1] for line in status.splitlines() if line.startswith("SigIgn:"))
    return bool(int(mask, 16) >> (signal.SIGINT - 1) & 1)


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


# -- the user guide documents the schema -----------------------------------------------------------
GUIDE = REPO / "docs" / "guide" / "experiments.md"


def test_guide_reference_is_generated_from_the_schema():
    from flyvpr.experiments.reference import _BEGIN, _END, reference_markdown

    text = GUIDE.read_text(encoding="utf-8")
    generated = text.split(_BEGIN, 1)[1].split(_END, 1)[0].strip()
    assert generated == reference_markdown().strip(), (
        "docs/guide/experiments.md is out of date: run "
        "python -m flyvpr.experiments.reference docs/guide/experiments.md"
    )


def test_every_schema_key_and_loader_option_is_documented():
    from flyvpr.datasets import DATASETS
    from flyvpr.experiments.config import DatasetBlock, ExperimentConfig, GridBlock, Settings
    from flyvpr.experiments.schema import schema_fields

    text = GUIDE.read_text(encoding="utf-8")
    for cls in (ExperimentConfig, Settings, DatasetBlock, GridBlock):
        for name, spec in schema_fields(cls):
            assert f"| `{name}` |" in text, f"{cls.__name__}.{name} is not in the guide"
            assert spec.doc and spec.value.expected
    options = {o for spec in DATASETS.values() for o in spec.options}
    assert options <= set(DatasetBlock.option_keys())  # a new loader option needs a schema key
    for kind in KINDS:
        assert f"| `{kind}` |" in text


def test_guide_example_config_is_valid(tmp_path):
    text = GUIDE.read_text(encoding="utf-8")
    example = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    config = parse_config(example, base_dir=tmp_path / "experiments")
    assert [len(config.grid_runs(g)) for g in config.grids] == [9, 3]
    assert config.datasets["sw"].resolved["root"] == str(
        (tmp_path / "experiments" / "../../shared/data/nordland_64x32").resolve()
    )
    refused = example.replace(
        'method_params = { flynet = { epochs = 100 }, "flynet+cann" = { epochs = 100 } }',
        "params = { epochs = 100 }",
    )
    with pytest.raises(ValueError, match=r"\('auc'\): 'epochs' is not a parameter of method 'pix"):
        parse_config(refused, base_dir=tmp_path)


def test_full_params_take_the_front_ends_hold_default():
    # a run's recorded filter arguments are those make_method would use: no hold behind
    # front ends whose scores repeat on sensor noise, unless the config asks for it
    from flyvpr.experiments.runs import full_params

    for method, held in (("kenyon+cann", True), ("flynet+cann", False), ("flyhash+cann", False)):
        _, filt = full_params(METHODS[method], {}, {})
        assert filt["hold_repeats"] is held
        assert make_method(method, 0, filter_params=filt).filter.hold_repeats is held
    _, filt = full_params(METHODS["flynet+cann"], {}, {"hold_repeats": True})
    assert filt["hold_repeats"] is True
    _, filt = full_params(METHODS["flynet+cann-paper"], {}, {})
    assert "hold_repeats" not in filt


def test_loky_worker_restarts_are_not_warned_of_other_warnings_are(recwarn):
    # loky recycles a worker whose memory grew past its leak threshold and warns from its own
    # module; the runs go on, so the runner leaves that warning out, and only that one
    import warnings

    from flyvpr.experiments import runner

    def warn(message, module):
        warnings.warn_explicit(message, UserWarning, "x.py", 1, module=module)

    loky = "joblib.externals.loky.process_executor"
    with runner._quiet_loky_restarts():
        warn(runner._LOKY_RESTART + ". This can be caused by ...", loky)
        warn("something else", loky)
        warn(runner._LOKY_RESTART, "somewhere.else")
    messages = [(str(w.message), w.filename) for w in recwarn]
    assert ("something else", "x.py") in messages
    assert sum(m.startswith(runner._LOKY_RESTART) for m, _ in messages) == 1  # the other module's
    recwarn.clear()
    warn(runner._LOKY_RESTART, loky)  # outside the runner the filter is gone
    assert len(recwarn) == 1
