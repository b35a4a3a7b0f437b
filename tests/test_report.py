"""The experiment report: HTML with embedded figures, Markdown with PNG files, protocol."""

from __future__ import annotations

import base64
import io
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
methods = ["flynet", "pixels"]
seeds = [0, 1]
method_params = { flynet = { epochs = 5 } }

[[grids]]
name = "time"
kind = "timing"
datasets = ["syn"]
methods = ["seqslam"]

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
    """An experiment folder with every kind of grid and one failed run (pixels has no
    training curve)."""
    folder = tmp_path_factory.mktemp("report")
    save_route(make_route(24, random_state=1), folder / "route")
    config = folder / "tiny.toml"
    config.write_text(textwrap.dedent(CONFIG), encoding="utf-8")
    summary = run_experiment(config, folder / "out", n_jobs=1, progress=False)
    assert len(summary["errors"]) == 2  # pixels in the training-curve grid, seeds 0 and 1
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


def test_report_tables_hold_every_method_and_the_failures(report):
    text = report[1].read_text(encoding="utf-8")
    for method in ("pixels", "flynet", "seqslam"):
        assert f"| {method} |" in text
    assert "## Failed runs" in text
    assert text.count("train-syn-pixels-s") == 2
    assert "accuracy_history_" in text
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
    script = REPO / "benchmarks" / "render_report.py"
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
