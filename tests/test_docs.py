"""The documentation: generated pages agree with their data, and the README stays short.

``make docs`` (part of ``make test``) builds the site with warnings as errors; these tests
check what the build cannot: that every generated page is what its JSON renders to now.
"""

import copy
import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def gen():
    return _load(DOCS / "generate_results.py", "_docs_generate_results")


def test_results_pages_and_readme_table_match_their_json(gen):
    stale = [str(p.relative_to(ROOT)) for p in gen.stale()]
    assert not stale, f"stale generated files {stale}: run python docs/generate_results.py"


def test_every_results_page_is_in_the_generator(gen):
    pages = {p.stem for p in (DOCS / "results").glob("*.md")} - {"index"}
    assert pages == {page.name for page in gen.PAGES}


def test_pipeline_figure_is_current():
    draw = _load(DOCS / "draw_pipeline.py", "_docs_draw_pipeline")
    assert draw.OUT.read_text() == draw.draw(), "run python docs/draw_pipeline.py"


def test_readme_is_short_and_speaks_to_users():
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) < 10_000
    for command in ("make demo", "make test"):
        assert command in text.split("\n## ")[0], f"{command} must come first in the README"


def test_no_issue_numbers_in_readme_or_docs():
    files = [ROOT / "README.md", ROOT / "CONTRIBUTING.md"]
    files += [p for p in DOCS.rglob("*") if p.suffix in {".md", ".rst", ".py"}]
    hits = [
        f"{p.relative_to(ROOT)}: {m.group(0)}"
        for p in files
        if p.is_file() and "_build" not in p.parts
        for m in re.finditer(r"issue [0-9]", p.read_text(), flags=re.IGNORECASE)
    ]
    assert not hits


def test_accuracy_numbers_come_from_the_json(gen):
    data = json.loads((ROOT / "benchmarks" / "accuracy.json").read_text())
    changed = copy.deepcopy(data)
    row = next(
        r for r in changed["summary"] if r["method"] == "pixels" and r["condition"] == "n64-0@20"
    )
    row["auc_mean"] = 0.123456
    page = gen.renderer(gen.PAGES[0], changed)(changed)
    assert "0.123" in page and page != gen.renderer(gen.PAGES[0], data)(data)
    table = gen.which_method_table(changed, ROOT / "README.md")
    assert "| `pixels` (single frames) | 0.12 |" in table


def test_which_method_table_from_a_benchmark_document(gen):
    def row(condition, method, seeds, mean, worst=None):
        return {
            "condition": condition,
            "method": method,
            "seeds": seeds,
            "auc_mean": mean,
            "auc_worst": mean if worst is None else worst,
        }

    summary = [
        row("n64-0@20", "flynet+cann", [0, 1], 0.5, 0.3),
        row("n64-0-1.5x@20", "flynet+cann", [0, 1], 0.4, 0.35),
        row("n64-0@20", "seqslam-20", [0], 0.25),
        row("n64-0@20", "netvlad+cann", [0], 0.75),
        row("vp-0@20", "kenyon+cann", [0, 1], 0.9, 0.875),
        row("n64-2000@20", "pixels+cann", [0, 1], 0.6, 0.5),
        row("other@20", "flynet", [0, 1], 0.1),
        row("r-walk-noisy@2", "flynet+cann-paper", [0, 1], 0.2, 0.1),
    ]
    data = {"conditions": [], "summary": summary, "bytes_per_place": {"kenyon+cann": 512}}
    table = gen.which_method_table(data, ROOT / "README.md")
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    assert rows == [
        "| `kenyon+cann` | - | - | - | 0.90 (0.88) | - | - | - | 512 |",
        "| `pixels+cann` | - | - | 0.60 (0.50) | - | - | - | - | - |",
        "| `flynet+cann` | 0.50 (0.30) | - | - | - | 0.40 (0.35) | - | - | - |",
        "| `flynet+cann-paper` (the paper's) | - | - | - | - | - | 0.20 (0.10) | - | - |",
        "| `netvlad+cann` | 0.75 | - | - | - | - | - | - | - |",
        "| `seqslam` (length 20, the paper's) | 0.25 | - | - | - | - | - | - | - |",
    ]
    assert "mean over 2 seeds, the worst seed in brackets; one value: one run" in table


def test_odometry_table_pairs_each_view_with_its_odometry_twin(gen):
    def row(condition, method, seeds, mean):
        return {"condition": condition, "method": method, "seeds": seeds, "auc_mean": mean}

    conditions = [
        {"view_key": "r-drops", "label": "dropped frames (±2)"},  # shown without the (±2)
        {"view_key": "r-drops-odo", "label": "dropped frames, odometry"},
        {"view_key": "r-walk", "label": "random walk"},
        {"view_key": "r-walk-odo", "label": "random walk, odometry"},
        {"view_key": "r-1x", "label": "1x"},  # no twin: no row
        {"view_key": "r-uneven", "label": "uneven"},  # a twin with no rows: no row
        {"view_key": "r-uneven-odo", "label": "uneven, odometry"},
    ]
    summary = [
        row("r-drops@2", "kenyon+cann", [0, 1], 0.6944),
        row("r-drops-odo@2", "kenyon+cann", [0, 1], 0.9702),
        row("r-drops@20", "kenyon+cann", [0, 1], 0.5),  # another tolerance: not shown
        row("r-drops@2", "pixels+cann", [0], 0.656),
        row("r-walk@2", "flynet+cann", [0, 1], 0.681),
        row("r-walk-odo@2", "flynet+cann", [0, 1], 0.923),
        row("r-1x@2", "kenyon+cann", [0, 1], 0.97),
        row("r-uneven@2", "kenyon+cann", [0, 1], 0.89),
    ]
    table = gen.odometry_table({"conditions": conditions, "summary": summary})
    rows = [line for line in table.splitlines() if line.startswith("| ") and "---" not in line]
    assert rows[1:] == [
        "| dropped frames | 0.694 / 0.970 | 0.656 / - | - / - |",
        "| random walk | - / - | - / - | 0.681 / 0.923 |",
    ]
    assert rows[0].startswith("| query | `kenyon+cann`: without / with |")
    assert "AUC at tolerance 2, mean over the seeds (2 for the methods with a seed)" in table


def test_seqslam_length_table_reads_each_window_and_length(gen):
    def row(condition, method, mean):
        return {"condition": condition, "method": method, "seeds": [0], "auc_mean": mean}

    summary = [
        row("n64-0@20", "seqslam-20", 0.8781),
        row("n64-0@20", "seqslam-60", 0.9755),
        row("n64-0@2", "seqslam-40", 0.5),  # another tolerance: not shown
        row("n64-1400@20", "seqslam-40", 0.9864),
        row("n64-1400@20", "seqslam-60 v0.25-3", 0.1),  # another speed range: not shown
    ]
    lines = gen.seqslam_length_table({"summary": summary}).splitlines()
    assert lines == [
        "| window | length 20 | length 40 | length 60 |",
        "|---|---|---|---|",
        "| frames 0-999 | 0.878 | - | 0.976 |",
        "| frames 1000-1999 | - | - | - |",
        "| frames 1400-2399 | - | 0.986 | - |",
    ]


_INDEX_ROW = {
    "queries": 200,
    "build_s": 0.3134,
    "query_ms_single": 2.5163,
    "query_ms_batched": 1.9,
    "recall_top_k": 0.11285,
    "true_place_in_top_k": 0.285,
    "index_mb": 69.04,
}


def test_indexes_table_marks_the_rows_with_a_note_and_gives_the_runs():
    from benchmarks import scale_indexes

    def row(places, index, queries=200, **extra):
        return dict(_INDEX_ROW, places=places, k=100, index=index, queries=queries, **extra)

    rows = [row(10**6, "mih r1"), row(10**7, "mih r2", 100, note="from a printed line")]
    rows.append(row(10**7, "exhaustive", 100, note="from a printed line"))
    table = scale_indexes.render_table({"rows": rows, "runs": ["--places 1000000", "x: y"]})
    lines = table.splitlines()
    assert lines[2] == "| 1,000,000 | mih r1 | 200 | 0.31 | 2.516 | 1.900 | 0.113 | 0.285 | 69 |"
    assert lines[3].startswith("| 10,000,000 | mih r2 (1) | 100 | 0.31 |")
    assert lines[4].startswith("| 10,000,000 | exhaustive (1) |")
    assert lines[5:] == [
        "",
        "k = 100.",
        "",
        "Runs:",
        "",
        "- --places 1000000",
        "- x: y",
        "",
        "(1) from a printed line.",
    ]
    bare = scale_indexes.render_table({"rows": rows[:1]})
    assert bare.splitlines()[-1] == "k = 100."


def test_indexes_append_refuses_a_file_that_is_not_its_document(tmp_path):
    from benchmarks import scale_indexes

    cases = {
        "broken.json": "{not json",
        "list.json": "[]",  # (the format before runs were kept)
        "rowless.json": '{"rows": [{"places": 1}]}',
        "binary.json": b"\xff\xfe\x00",
    }
    for name, text in cases.items():
        path = tmp_path / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(ValueError, match=f"^--append: .*{name}"):
            scale_indexes.read_document(path)
    with pytest.raises(ValueError, match="cannot read"):
        scale_indexes.read_document(tmp_path)  # a folder
    good = tmp_path / "good.json"
    good.write_text('{"runs": ["a"], "rows": [{"places": 1, "index": "x", "k": 5}]}')
    assert scale_indexes.read_document(good)["runs"] == ["a"]
    # the command line: a clear error and exit 2 before any data is read
    bad = tmp_path / "broken.json"
    before = bad.read_bytes()
    with pytest.raises(SystemExit) as exit_:
        scale_indexes.main(["--places", "10", "--json", str(bad), "--append"])
    assert exit_.value.code == 2 and bad.read_bytes() == before


def test_indexes_document_keeps_the_earlier_runs_and_replaces_rows_measured_again():
    from benchmarks import scale_indexes

    line = scale_indexes.run_line([100000, 10**6], 200, 100, ["faiss-hnsw"])
    assert line == "--places 100000 --places 1000000 --queries 200 --k 100 --skip faiss-hnsw"
    first = scale_indexes.document([{"places": 10, "index": "a", "k": 5}], "one")
    assert first == {
        "what": scale_indexes.WHAT,
        "runs": ["one"],
        "rows": [{"places": 10, "index": "a", "k": 5}],
    }
    first["rows"].append({"places": 10, "index": "b", "k": 5})
    again = [
        {"places": 10, "index": "a", "k": 5, "new": True},
        {"places": 20, "index": "a", "k": 5},
    ]
    doc = scale_indexes.document(again, "two", first)
    assert doc["runs"] == ["one", "two"]
    assert doc["rows"] == [{"places": 10, "index": "b", "k": 5}, *again]
    assert (
        scale_indexes.render_table(
            {"rows": [dict(r, **_INDEX_ROW) for r in doc["rows"]], "runs": doc["runs"]}
        ).count("| 10 |")
        == 2
    )


def test_which_method_table_links_relative_to_its_file(gen):
    data = json.loads((ROOT / "benchmarks" / "accuracy.json").read_text())
    assert "(docs/results/accuracy.md)" in gen.which_method_table(data, ROOT / "README.md")
    guide = DOCS / "guide" / "methods.md"
    assert "(../results/accuracy.md)" in gen.which_method_table(data, guide)


def test_block_markers_are_required(gen, tmp_path):
    path = tmp_path / "page.md"
    path.write_text("# no markers\n")
    with pytest.raises(ValueError, match="must contain the lines"):
        gen.render_block(path, {"summary": []})


def test_missing_json_gives_a_page_that_says_how_to_make_it(gen):
    page = gen.Page("x", "X", "benchmarks/does-not-exist.json", "python make_it.py", None)
    text = gen.render_page(page)
    assert text.startswith("# X\n") and "Not measured yet" in text and "python make_it.py" in text


def test_speed_page_lists_every_figure_of_the_json():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        speed = _load(ROOT / "benchmarks" / "speed.py", "_docs_speed")
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    data = json.loads((ROOT / "benchmarks" / "speed.json").read_text())
    data = {**data, "new_figure_s": 1.2345, "decode_s": 9.876}
    page = speed.render_markdown(data)
    assert "| `new_figure_s` | 1.234 |" in page or "| `new_figure_s` | 1.235 |" in page
    assert "| `decode_s` | 9.876 |" in page
    assert data["machine"]["cpu"] in page
    assert not re.search(r"^# ", page, flags=re.MULTILINE), "headings start at level 2"


def test_api_pages_document_every_public_name_once(tmp_path):
    sys.path.insert(0, str(DOCS))
    try:
        api = _load(DOCS / "api_pages.py", "_docs_api_pages")
        names = api.write_api_pages(tmp_path)
    finally:
        sys.path.remove(str(DOCS))
    assert "flyvpr" in names and "flyvpr.frontends" in names
    text = "".join((tmp_path / f"{n}.rst").read_text() for n in names)
    documented = re.findall(r"^\.\. auto(?:class|function|data|exception):: (\S+)", text, re.M)
    assert len(documented) == len(set(documented))
    import flyvpr.frontends
    import flyvpr.temporal

    for package in (flyvpr.frontends, flyvpr.temporal):
        for name in package.__all__:
            assert f"{package.__name__}.{name}" in documented


TINY_EXPERIMENT = """
title = "Tiny"

[[datasets]]
name = "syn"
label = "synthetic summer -> winter"
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
methods = ["pixels"]
"""


def test_paper_page_data_from_a_results_folder(gen, tmp_path):
    from flyvpr.experiments import run_experiment
    from flyvpr.synthetic import make_route, save_route

    save_route(make_route(12, random_state=1), tmp_path / "route")
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_EXPERIMENT, encoding="utf-8")
    run_experiment(config, tmp_path / "out", n_jobs=1, progress=False)
    data = gen.paper_summary(tmp_path / "out")
    json.dumps(data)  # the page's JSON
    types = {b["type"] for b in data["blocks"]}
    assert "figure" not in types and "code" not in types
    headings = [b for b in data["blocks"] if b["type"] == "heading"]
    assert min(h["level"] for h in headings) == 2
    assert "Contents" not in {h["text"] for h in headings}
    assert str(tmp_path) not in json.dumps(data), "no path of the machine that ran it"
    page = gen.ADAPTERS["paper"](data)
    assert "## Single frame" in page and "| pixels |" in page.replace("|  ", "| ")


def _scale_row(**kidnap):
    row = {
        "places": 100000,
        "index": "mih",
        "frames_per_s": 1000.0,
        "tracked_frames_per_s": 2000.0,
        "searched_ms_per_frame": 5.0,
        "localized_share": 0.9,
        "searched_share": 0.05,
        "same_place_within_20_share": 0.99,
        "peak_rss_mb": 100.0,
        "build_s": 1.0,
        "open_s": 0.001,
        "lock_frames": 9,
        "kidnap_trials": 200,
        "kidnap_relocated_share": 0.88,
        "kidnap_frames_median": 12.0,
        "kidnap_searched_share": 0.7,
        "kidnap_ms_per_search": 1.5,
    }
    row.update(kidnap)
    return row


def test_scale_kidnap_table_gives_the_trials_and_the_interval(gen):
    _, kidnap = gen.scale_tables([_scale_row(kidnap_relocated_ci95=[0.827, 0.918])])
    assert "| 100,000 | mih | 200 | 0.88 (0.83-0.92) | 12.0 | 0.70 | 1.50 |" in kidnap
    # rows of runs before the interval was written: the share alone
    _, kidnap = gen.scale_tables([_scale_row(kidnap_trials=50)])
    assert "| 100,000 | mih | 50 | 0.88 | 12.0 |" in kidnap


def test_large_calibration_table_lines_up_the_localizers(gen):
    def cal(rows, lost=None):
        entry = {
            "reliability": [{"bin": b, "n": n, "confidence": c, "right": r} for b, n, c, r in rows]
        }
        if lost is not None:
            entry.update(
                lost_frames=lost[0], lost_mean_confidence=lost[1], lost_right_share=lost[2]
            )
        return entry

    mih = {
        "summary": {
            "calibration_tol2": {
                "whole_map": cal([("0.1-0.2", 10, 0.12, 0.1), ("0.9-1.0", 990, 0.99, 1.0)]),
                "windowed": cal([("0.9-1.0", 1000, 0.98, 0.995)], (40, 0.61, 0.7)),
            }
        }
    }
    exact = {
        "summary": {
            "calibration_tol2": {"windowed": cal([("0.5-0.6", 3, 0.55, 1 / 3)], (3, 0.55, 0.333))}
        }
    }
    table = gen.large_calibration_table(mih, exact)
    lines = table.splitlines()
    assert lines[0].count("answers, confidence, right") == 3
    assert "| 0.1-0.2 | 10, 0.12, 0.10 | - | - |" in lines
    assert "| 0.5-0.6 | - | - | 3, 0.55, 0.33 |" in lines
    assert "| 0.9-1.0 | 990, 0.99, 1.00 | 1,000, 0.98, 0.99 | - |" in lines
    assert "| `mih` | 40 | 0.61 | 0.70 |" in lines and "| exact scan | 3 | 0.55 | 0.33 |" in lines
    # runs made before the calibration was written
    assert gen.large_calibration_table({"summary": {}}, None) == "(no calibration in these runs)"


def test_the_localized_threshold_the_docs_state_is_the_tables():
    # `localized` is a raw confidence of 0.5 or more, so a calibrated one of at least the
    # default table's value at 0.5 ** 0.25 (the table is given at the raw confidence's
    # fourth root): the README, the robot and model-file guides and the Localizer's docstring
    # say that number, rounded down to 4 decimals (every localized answer's confidence is at
    # least the stated one; rounded up, answers just above the level were localized below
    # it), and a refitted table must bring them along.
    import math

    import numpy as np

    from flyvpr.temporal.cann._filter import CALIBRATION

    level = float(np.interp(0.5**0.25, np.linspace(0.0, 1.0, 11), CALIBRATION))
    stated = f"{math.floor(level * 1e4) / 1e4:.4f}"
    sources = [
        ROOT / "README.md",
        DOCS / "guide" / "robot.md",
        DOCS / "guide" / "model-files.md",
        ROOT / "src" / "flyvpr" / "localization" / "localizer.py",
    ]
    for path in sources:
        text = " ".join(path.read_text(encoding="utf-8").split())
        claims = re.findall(r"confidence (?:of )?(\d\.\d+) or more", text)
        assert claims, f"{path.name} no longer states the localized threshold"
        assert set(claims) == {stated}, (path.name, claims, level)


def test_machine_sentence_leaves_out_empty_fields():
    from benchmarks._common import machine_sentence

    data = {"machine": {"machine": "x86_64", "processor": "", "cpu_count": 2, "gpu": None}}
    assert machine_sentence(data) == "Machine: machine x86_64, cpu_count 2."
    assert machine_sentence({"machine": {}}) == machine_sentence({}) == ""
