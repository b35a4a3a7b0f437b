"""The experiment report: HTML with embedded figures, Markdown with PNG files, protocol."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from flyvpr.experiments import run_experiment, write_report
from flyvpr.synthetic import make_route, save_route

REPO = Path(__file__).resolve().parents[1]

CONFIG = """
title = "Tiny report"
description = "A synthetic route, every kind of grid."

[settings]
cache = "cache"

[[datasets]]
name = "syn"
label = "synthetic summer → winter"
loader = "nordland"
root = "route"
reference = "summer"
query = "winter"
tolerance = 2

[[grids]]
name = "eval"
kind = "evaluate"
title = "Single frame"
datasets = ["syn"]
methods = ["pixels", "flynet"]
seeds = [0, 1]
method_params = { flynet = { epochs = 5 } }

[[grids]]
name = "sens"
kind = "sensitivity"
datasets = ["syn"]
methods = ["flynet"]
seeds = [0]
params = { wta_ratio = [0.25, 0.5], epochs = 5 }

[[grids]]
name = "curves"
kind = "training_curve"
datasets = ["syn"]
methods = ["flynet", "flynet+cann"]
seeds = [0, 1]
method_params = { flynet = { epochs = 5 }, "flynet+cann" = { epochs = 2, n_hidden = 0 } }

[[grids]]
name = "time"
kind = "timing"
datasets = ["syn"]
methods = ["seqslam"]

[[grids]]
name = "cold"
kind = "timing"
datasets = ["syn"]
methods = ["pixels"]
warmup = false

[[grids]]
name = "size"
kind = "footprint"
datasets = ["syn"]
methods = ["pixels", "flynet"]
seeds = [0, 1]
method_params = { flynet = { epochs = 5 } }

[[grids]]
name = "examples"
kind = "qualitative"
datasets = ["syn"]
methods = ["pixels", "flynet"]
method_params = { flynet = { epochs = 5 } }
examples = 3
"""

FIGURES = {
    "eval_auc",
    "eval_pr",
    "sens_sensitivity",
    "curves_training",
    "size_size",
    "examples_syn_examples",
}


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """An experiment folder with every kind of grid and a failed run (flynet+cann in the
    training-curve grid with n_hidden = 0, which its front end refuses when it fits)."""
    folder = tmp_path_factory.mktemp("report")
    save_route(make_route(24, random_state=1), folder / "route")
    config = folder / "tiny.toml"
    config.write_text(textwrap.dedent(CONFIG), encoding="utf-8")
    summary = run_experiment(config, folder / "out", n_jobs=1, progress=False)
    assert len(summary["errors"]) == 2  # flynet+cann in the training-curve grid, seeds 0, 1
    return folder / "out"


@pytest.fixture(scope="module")
def report(results) -> tuple[Path, Path]:
    pytest.importorskip("matplotlib")
    return write_report(results)


def test_report_files(report, results):
    html_path, md_path = report
    assert html_path == results / "report.html" and md_path == results / "report.md"
    assert {p.stem for p in (results / "figures").glob("*.png")} == FIGURES


def test_html_is_self_contained_with_every_figure_embedded(report):
    from PIL import Image

    text = report[0].read_text(encoding="utf-8")
    images = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(images) == len(FIGURES) == text.count("<img")
    for data in images:
        with Image.open(io.BytesIO(base64.b64decode(data))) as im:
            assert im.format == "PNG" and im.width >= 400
    # nothing loaded from elsewhere
    assert not re.search(r'(src|href)="(https?:|file:|//)', text)
    assert "<link" not in text and "<script" not in text


def test_markdown_references_the_figure_files(report, results):
    text = report[1].read_text(encoding="utf-8")
    linked = re.findall(r"!\[[^\]]*\]\((figures/[^)]+\.png)\)", text)
    assert {Path(p).stem for p in linked} == FIGURES
    assert all((results / p).is_file() for p in linked)
    assert "| condition | method | AUC (%)" in text


def test_report_states_the_protocol_and_machine(report):
    text = report[0].read_text(encoding="utf-8")
    for fact in (
        "reference=summer query=winter",
        "positions 0..23",
        "24 references x 24 queries",
        "tolerance 2 frames",
        "Seeds: [0, 1]",
        "32x64",
        "python",
        "numpy",
    ):
        assert fact in text, fact
    from flyvpr.experiments.runner import machine_info

    assert machine_info()["cpu"] in text


UNEQUAL = """
title = "A longer query traverse"

[settings]
cache = "cache"

[[datasets]]
name = "longer"
loader = "generic"
root = "route"
reference = "summer"
query = "winter"
tolerance = 2

[[grids]]
name = "eval"
kind = "evaluate"
datasets = ["longer"]
methods = ["pixels"]
"""


def test_report_of_traverses_of_other_lengths_and_queries_without_a_match(tmp_path):
    # 18 references, 24 queries: queries 20..23 lie beyond the reference's last place + 2
    save_route(make_route(24, random_state=1), tmp_path / "route")
    for path in sorted((tmp_path / "route" / "summer").iterdir())[18:]:
        path.unlink()
    config = tmp_path / "unequal.toml"
    config.write_text(textwrap.dedent(UNEQUAL), encoding="utf-8")
    out = tmp_path / "out"
    run_experiment(config, out, progress=False)
    _, md_path = write_report(out, figures=False)
    text = md_path.read_text(encoding="utf-8")
    assert (
        "reference positions 0..17, query positions 0..23, 18 references x 24 queries "
        "(20 with a true match), tolerance 2 frames"
    ) in text
    # R@1 is counted over the queries that have a match, as the table prints it
    assert "share of queries whose" not in text
    assert "R@1 the share of matchable queries whose best match is correct" in text
    record = json.loads(_a_run_file(out, "evaluate-longer-pixels-s0-").read_text())
    assert record["protocol"]["n_query_with_match"] == 20
    result = record["result"]
    assert result["n_query_with_match"] == 20
    assert result["recall_at_1"] == sum(record["correct"]) / result["n_query_with_match"]
    auc, r1 = 100 * result["auc"], 100 * result["recall_at_1"]
    assert f"| longer | pixels | {auc:.1f} | {r1:.1f} |" in text  # (one seed: no spread)


def test_report_tables_hold_every_method_and_the_failures(report):
    text = report[1].read_text(encoding="utf-8")
    for method in ("pixels", "flynet", "seqslam"):
        assert f"| {method} |" in text
    assert "## Failed runs" in text
    assert text.count("train-syn-flynet+cann-s") == 2
    assert "n_hidden must be >= 1" in text
    assert "feature extraction (s)" in text and "trained params" in text


def test_report_without_figures(results, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(results, copy)
    shutil.rmtree(copy / "figures", ignore_errors=True)
    html_path, md_path = write_report(copy, figures=False)
    assert "<img" not in html_path.read_text(encoding="utf-8")
    assert "| flynet |" in md_path.read_text(encoding="utf-8")
    assert not (copy / "figures").exists()


def test_missing_matplotlib_names_the_extra(results, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ImportError, match=r"pip install 'flyvpr\[plot\]'"):
        write_report(results)


def test_missing_results_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="results folder not found"):
        write_report(tmp_path / "nothing", figures=False)
    with pytest.raises(FileNotFoundError, match="experiment.json"):
        write_report(tmp_path, figures=False)


def test_report_renders_in_chromium(report, tmp_path):
    script = REPO / "docs" / "render_report.py"
    browsers = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
    if not any(shutil.which(b) for b in browsers):
        pytest.skip("no Chromium/Chrome on PATH")
    shot = tmp_path / "shot.png"
    proc = subprocess.run(
        [
            sys.executable,
            str(script),
            str(report[0]),
            "--screenshot",
            str(shot),
            "--height",
            "2000",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"{len(FIGURES)}/{len(FIGURES)} images decoded" in proc.stdout
    assert shot.is_file()


def test_report_follows_the_plan_stored_at_experiment_time(results, tmp_path, monkeypatch):
    # A constructor default changed since the experiment ran: re-expanding the grids now
    # would give other run ids, yet the report must still show the runs that were made.
    import flyvpr.experiments.runs as runs_module

    real = runs_module._defaults
    monkeypatch.setattr(runs_module, "_defaults", lambda cls: {**real(cls), "new_default": 1})
    copy = tmp_path / "copy"
    shutil.copytree(results, copy)
    _, md_path = write_report(copy, figures=False)
    text = md_path.read_text(encoding="utf-8")
    assert "0 not run" in text
    assert "belong to no grid" not in text


# -- faults: a results folder whose files are not what they should be ----------------------------
def _edit_json(path: Path, edit) -> None:
    record = json.loads(path.read_text(encoding="utf-8"))
    edit(record)
    path.write_text(json.dumps(record), encoding="utf-8")


def _a_run_file(folder: Path, prefix: str = "evaluate-syn-pixels-s0-") -> Path:
    return next((folder / "runs").glob(f"{prefix}*.json"))


FAULTS = {
    "experiment-empty-object": (
        lambda d: (d / "experiment.json").write_text("{}"),
        "experiment.json",
        r"expected the record of `flyvpr experiment` with key 'config_text'; it has none",
    ),
    "experiment-truncated": (
        lambda d: (d / "experiment.json").write_text((d / "experiment.json").read_text()[:50]),
        "experiment.json",
        r"not valid JSON .*truncated or garbled",
    ),
    "experiment-plan-of-another-grid": (
        lambda d: _edit_json(
            d / "experiment.json", lambda r: r["plan"]["eval"][0].update(method="seqslam")
        ),
        "experiment.json",
        r"plan\.eval lists run .* which grid 'eval' of its config_text does not have",
    ),
    "experiment-config-text-broken": (
        lambda d: _edit_json(d / "experiment.json", lambda r: r.update(config_text="x = ")),
        "experiment.json",
        r"\(config_text\): not valid TOML",
    ),
    "run-without-result": (
        lambda d: _edit_json(_a_run_file(d), lambda r: r.pop("result")),
        "run",
        r"with key 'result' \(a finished evaluate run\); it has none",
    ),
    "run-without-auc": (
        lambda d: _edit_json(_a_run_file(d), lambda r: r["result"].pop("auc")),
        "run",
        r"with key 'result.auc'",
    ),
    "run-auc-a-string": (
        lambda d: _edit_json(_a_run_file(d), lambda r: r["result"].update(auc="high")),
        "run",
        r"its 'result.auc' must be a number or null, got \"high\"",
    ),
    "run-truncated": (
        lambda d: _a_run_file(d).write_text(_a_run_file(d).read_text()[:200]),
        "run",
        r"expected a run file of `flyvpr experiment` \(JSON\); it is not valid JSON",
    ),
    "run-garbled-bytes": (
        lambda d: _a_run_file(d).write_bytes(b"\x80\x81" * 50),
        "run",
        r"line 1: not UTF-8 text \(byte 0x80\)",
    ),
    "run-of-another-name": (
        lambda d: _a_run_file(d).rename(d / "runs" / "evaluate-syn-pixels-s0-000000000000.json"),
        "evaluate-syn-pixels-s0-000000000000.json",
        r"holds run 'evaluate-syn-pixels-s0-\w+', not the run its name says",
    ),
    "training-run-without-history": (
        lambda d: _edit_json(
            _a_run_file(d, "train-syn-flynet-s0-"), lambda r: r["result"].pop("accuracy_history")
        ),
        "train-syn-flynet-s0-",
        r"with key 'result.accuracy_history' \(a finished train run\)",
    ),
    "failed-run-without-error": (
        lambda d: _edit_json(_a_run_file(d, "train-syn-flynet+cann-s0-"), lambda r: r.pop("error")),
        "train-syn-flynet+cann-s0-",
        r"with key 'error' \(status 'error'\)",
    ),
}


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_a_broken_results_file_is_named_in_one_line(results, tmp_path, capsys, fault):
    from flyvpr.cli import main

    damage, file_hint, match = FAULTS[fault]
    copy = tmp_path / "copy"
    shutil.copytree(results, copy)
    for name in ("report.html", "report.md"):
        (copy / name).unlink(missing_ok=True)
    damage(copy)
    with pytest.raises(ValueError, match=match) as info:
        write_report(copy, figures=False)
    named = str(info.value).split(": ", 1)[0]
    assert named.startswith(str(copy)) and file_hint in named, str(info.value)
    assert main(["report", str(copy), "--no-figures"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and named in err and "Traceback" not in err
    assert not (copy / "report.html").exists() and not (copy / "report.md").exists()


def test_html_escapes_every_text():
    from flyvpr.experiments.document import Document

    doc = Document('<b>"title"</b>')
    doc.heading(1, "<script>alert(1)</script>", anchor='x" onclick="y')
    doc.table(["<th>"], [["a & b"]], caption="<i>")
    doc.items([("<li>", "a<b")])
    text = doc.html()
    assert "<script>alert" not in text and "&lt;script&gt;alert(1)&lt;/script&gt;" in text
    assert "<b>" not in text and 'onclick="y' not in text and "a &amp; b" in text
    assert "<th>&lt;th&gt;</th>" in text and "<caption>&lt;i&gt;</caption>" in text
    # Markdown is not HTML: text stays as written, but a | in a cell cannot split the table
    doc.table(["a|b"], [["c\nd"]])
    assert "| a\\|b |\n|---|\n| c d |" in doc.markdown("figures")


def test_templates_ship_as_package_data():
    from importlib import resources

    import tomllib

    globs = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["flyvpr.experiments"]
    folder = resources.files("flyvpr.experiments") / "templates"
    names = {p.name for p in folder.iterdir() if not p.name.startswith(".")}
    shipped = {n for n in names if any(Path(n).match(Path(g).name) for g in globs)}
    assert names and shipped == names


def test_every_result_file_follows_the_umask(report, results):
    # Everything in the results folder goes through flyvpr._io's atomic writers: no file is
    # left half-written or as a temporary, and each gets the umask's permissions (0644 under 022).
    import os

    umask = os.umask(0)
    os.umask(umask)
    written = [p for p in results.rglob("*") if p.is_file() and "cache" not in p.parts]
    names = {p.relative_to(results).parts[0] for p in written}
    expected = {"experiment.json", "config.toml", "runs", "figures", "report.html", "report.md"}
    assert names == expected
    assert {p: p.stat().st_mode & 0o777 for p in written} == {p: 0o666 & ~umask for p in written}
    assert not [p for p in written if p.name.endswith(".tmp")]


def test_build_report_writes_nothing(results):
    from flyvpr.experiments.report import build_report

    before = sorted(p.name for p in results.iterdir())
    doc = build_report(results, figures=False)
    assert sorted(p.name for p in results.iterdir()) == before
    assert doc.figures == {} and any(b["type"] == "table" for b in doc.blocks)


def test_timing_tables_say_whether_the_runs_were_warmed_up(report):
    md = report[1].read_text(encoding="utf-8")
    assert "after a warm-up (the method run untimed on 100 frames first)" in md
    assert "without a warm-up (warmup = false" in md
    # one caption each: the warmed grid does not claim the cold one's and the other way round
    assert md.count("after a warm-up") == 1 and md.count("without a warm-up") == 1


SPEEDS = """
title = "A thinned query and the whole one"

[settings]
cache = "cache"

[[datasets]]
name = "syn"
loader = "generic"
root = "route"
reference = "summer"
query = "winter"
tolerance = 2

[[grids]]
name = "fast"
kind = "evaluate"
datasets = ["syn"]
methods = ["pixels"]
speed = 2

[[grids]]
name = "all"
kind = "evaluate"
datasets = ["syn"]
methods = ["pixels"]
"""


def test_each_grid_states_its_own_protocol_and_the_data_section_the_whole_traverse(tmp_path):
    # the grid that thins the query by speed comes first: its protocol was the dataset's
    # for every grid and for the data section
    save_route(make_route(24, random_state=1), tmp_path / "route")
    config = tmp_path / "speeds.toml"
    config.write_text(textwrap.dedent(SPEEDS), encoding="utf-8")
    run_experiment(config, tmp_path / "out", progress=False)
    _, md_path = write_report(tmp_path / "out", figures=False)
    lines = md_path.read_text(encoding="utf-8").splitlines()
    whole = "positions 0..23, 24 references x 24 queries, tolerance 2 frames"
    thinned = "24 references x 12 queries, tolerance 2 frames, 12 of 24 query frames"
    grid_lines = [line for line in lines if line.startswith("Data: ")]
    assert len(grid_lines) == 2
    assert thinned in grid_lines[0] and whole not in grid_lines[0]
    assert whole in grid_lines[1] and "query frames" not in grid_lines[1]
    data = lines[lines.index("## Protocol: data") :]
    (row,) = [line for line in data if line.startswith("| syn |")]
    assert whole in row and "query frames" not in row
