"""Turn an experiment's run files into ``report.html`` and ``report.md``.

``DIR/report.html`` is self-contained (figures embedded as base64 PNG); it
holds one section per grid of the config (tables and figures by the grid's
kind, :mod:`flyvpr.experiments.sections`), the protocol of every number
(data, frame range, reference and query roles, tolerance, image size, seeds,
parameters) and the machines the runs used.  ``DIR/report.md`` holds the same
text and tables, with the figures as PNG files in ``DIR/figures/``.  Both are
rendered from one :class:`~flyvpr.experiments.document.Document` by Jinja2
templates.

Every file of the results folder is checked as it is read
(:mod:`flyvpr.experiments.records`): a broken one stops the report with one
line naming it, rather than a table that silently lacks its run.
"""

from __future__ import annotations

import json
import logging
from datetime import datetime, timezone
from pathlib import Path

from .._io import write_bytes_atomic, write_text_atomic
from .config import ExperimentConfig, parse_config
from .document import Document
from .records import read_experiment, read_run
from .sections import SECTIONS, GridRuns

__all__ = ["write_report", "build_report", "load_results"]

logger = logging.getLogger(__name__)


# -- loading -------------------------------------------------------------------------------------
def load_results(results_dir) -> tuple[ExperimentConfig, dict, dict]:
    """Read ``experiment.json`` and every run file of a results folder.

    Returns
    -------
    config : ExperimentConfig
        The config of the latest ``flyvpr experiment`` into this folder.
    experiment : dict
        ``experiment.json`` (sessions, machines).
    records : dict
        run id -> run record, for every file in ``runs/``.

    Raises
    ------
    FileNotFoundError
        If the folder or its ``experiment.json`` is missing.
    ValueError
        If ``experiment.json``, its config or a run file is broken: not UTF-8,
        not JSON, or without a key the report reads (the message names the
        file and the key).
    """
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise FileNotFoundError(f"results folder not found: {results_dir}")
    exp_file = results_dir / "experiment.json"
    if not exp_file.is_file():
        raise FileNotFoundError(
            f"{exp_file} is missing: is {results_dir} the --out folder of `flyvpr experiment`?"
        )
    experiment = read_experiment(exp_file)
    stored = experiment["config"]
    config = parse_config(
        experiment["config_text"],
        base_dir=stored["base_dir"],
        source=f"{exp_file} (config_text)",
        path=stored.get("path"),
    )
    _check_plan(experiment.get("plan"), config, exp_file)
    records = {}
    for path in sorted((results_dir / "runs").glob("*.json")):
        record = read_run(path)
        records[record["run_id"]] = record
    return config, experiment, records


def _check_plan(plan: dict | None, config: ExperimentConfig, path: Path) -> None:
    """A plan the report follows must name runs its own config's grids can have."""
    if not plan or set(plan) != {g.name for g in config.grids}:
        return  # no plan, or another config's: the report expands the grids itself
    for grid in config.grids:
        for entry in plan[grid.name]:
            if (
                entry["dataset"] not in grid.datasets
                or entry["method"] not in grid.methods
                or entry["seed"] not in grid.seeds_for(entry["method"])
            ):
                raise ValueError(
                    f"{path}: plan.{grid.name} lists run {entry['run_id']!r} "
                    f"({entry['dataset']}, {entry['method']}, seed {entry['seed']}), which grid "
                    f"{grid.name!r} of its config_text does not have"
                )


def _tolerance_text(tol) -> str:
    if isinstance(tol, dict) and tol:
        return ", ".join(f"{v} {k}" for k, v in tol.items())
    return "-" if tol is None else str(tol)


def _protocol_line(g: GridRuns, records_protocols: dict) -> str:
    grid = g.grid
    parts = []
    for name in grid.datasets:
        ds = g.config.datasets[name]
        proto = records_protocols.get(name)
        parts.append(f"{ds.label}: {_dataset_protocol_text(ds, proto)}")
    params = {k: v for k, v in grid.params.items()}
    text = "Data: " + "; ".join(parts) + ". "
    text += f"Methods: {', '.join(grid.methods)}. Seeds: {list(grid.seeds)}"
    if grid.method_seeds:
        text += " (" + "; ".join(f"{m}: {list(s)}" for m, s in grid.method_seeds.items()) + ")"
    text += ". "
    if params:
        text += f"Parameters: {json.dumps(params)}. "
    if grid.method_params:
        text += f"Per-method parameters: {json.dumps(grid.method_params)}. "
    if grid.speed is not None:
        text += f"Query speed profile: {grid.speed} places per frame (seeded by the run's seed). "
    size = g.config.settings.image_size
    text += f"Images: gray, {size[0]}x{size[1]} (HxW). "
    n_ok = len(g.ok)
    text += f"Runs finished: {n_ok} of {len(g.items)}."
    return text


def _dataset_protocol_text(ds, proto: dict | None) -> str:
    if proto is None:
        opts = ds.options
        return (
            f"{ds.loader} {opts.get('reference', '?')} -> {opts.get('query', '?')} "
            f"(no finished run yet)"
        )
    first = proto.get("first", 0) or 0
    n_ref, n_query = proto.get("n_reference"), proto.get("n_query")
    rng = proto.get("frame_number_range")
    if not n_ref:
        frames = "all frames"
    elif n_query == n_ref and not proto.get("query_subset"):
        frames = f"positions {first}..{first + n_ref - 1}"
    else:  # traverses of other lengths; a query subset (speed) says which it kept below
        frames = f"reference positions {first}..{first + n_ref - 1}"
        if n_query and not proto.get("query_subset"):
            frames += f", query positions {first}..{first + n_query - 1}"
    if rng:
        frames += f" (file frames {rng[0]}..{rng[1]})"
    text = (
        f"{proto.get('dataset')} reference={proto.get('reference')} query={proto.get('query')}, "
        f"{frames}, {n_ref} references x {n_query} queries"
    )
    matchable = proto.get("n_query_with_match")  # (absent from older run files)
    if matchable is not None and matchable != n_query:
        text += f" ({matchable} with a true match)"
    text += f", tolerance {_tolerance_text(proto.get('tolerance'))}"
    if proto.get("query_subset"):
        text += f", {proto['query_subset']}"
    return text


# -- the report ----------------------------------------------------------------------------------
def _build(config: ExperimentConfig, experiment: dict, records: dict, figures: bool) -> Document:
    from .._version import __version__

    doc = Document(config.title)
    doc.heading(1, config.title)
    if config.description:
        doc.para(config.description)
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    doc.para(
        f"Generated {now} by flyvpr {__version__} from {experiment.get('config_path')}. "
        "Reproduce with: flyvpr experiment CONFIG --out DIR && flyvpr report DIR.",
        "muted",
    )

    plan = experiment.get("plan") or {}
    if set(plan) == {g.name for g in config.grids}:
        all_ids = {item["run_id"] for items in plan.values() for item in items}
    else:  # an experiment.json without a plan (or another config's): expand the grids now
        plan = {}
        all_ids = {r.run_id for r in config.runs()}
    mine = {k: v for k, v in records.items() if k in all_ids}
    n_ok = sum(1 for r in mine.values() if r["status"] == "ok")
    n_missing = len(all_ids) - len(mine)
    summary = (
        f"{len(all_ids)} distinct runs: {n_ok} finished, {len(mine) - n_ok} failed, "
        f"{n_missing} not run."
    )
    if len(records) > len(mine):
        summary += (
            f" {len(records) - len(mine)} run file(s) in runs/ belong to no grid of this "
            "config (ignored)."
        )
    doc.para(summary)

    grids = [GridRuns(config, grid, records, plan.get(grid.name)) for grid in config.grids]
    doc.heading(2, "Contents")
    doc.items(
        [(f"{grid.title} ({grid.kind})", f"grid-{grid.name}") for grid in config.grids]
        + [
            ("Protocol: data", "data"),
            ("Protocol: machines", "machines"),
            ("Failed runs", "errors"),
        ]
    )

    order: list[str] = []  # every method keeps one colour across the figures
    for grid in config.grids:
        order += [m for m in grid.methods if m not in order]
    for g in grids:
        doc.heading(2, g.grid.title, anchor=f"grid-{g.grid.name}")
        if g.grid.description:
            doc.para(g.grid.description)
        doc.para(_protocol_line(g, _protocols([g])), "protocol")
        if not g.ok:
            doc.para("No finished run in this grid yet.", "error")
            continue
        SECTIONS[g.grid.kind](doc, g, figures, order)

    _data_section(doc, config, _protocols(grids))
    _machines_section(doc, mine, experiment["sessions"])
    doc.heading(2, "Failed runs", anchor="errors")
    failed = [r for r in mine.values() if r["status"] != "ok"]
    if failed:
        doc.table(["run", "error"], [[r["run_id"], r["error"]] for r in failed])
    else:
        doc.para("None.")
    doc.heading(2, "Configuration")
    doc.code(config.text.strip())
    return doc


def _protocols(grids: list[GridRuns]) -> dict[str, dict]:
    """Each dataset's protocol, from the first finished run of ``grids`` on it that took the
    whole query traverse (a grid's ``speed`` keeps a subset of it), or else from the first."""
    protocols: dict[str, dict] = {}
    for g in grids:
        for item in g.ok:
            proto = item["record"]["protocol"]
            held = protocols.get(item["dataset"])
            if held is None or (held.get("query_subset") and not proto.get("query_subset")):
                protocols[item["dataset"]] = proto
    return protocols


def _data_section(doc: Document, config: ExperimentConfig, protocols: dict) -> None:
    doc.heading(2, "Protocol: data", anchor="data")
    rows = [
        [
            name,
            ds.label,
            ds.loader,
            str(ds.options.get("root", "")),
            _dataset_protocol_text(ds, protocols.get(name)),
        ]
        for name, ds in config.datasets.items()
    ]
    doc.table(["dataset", "label", "loader", "root (as configured)", "protocol"], rows)
    size = config.settings.image_size
    doc.para(
        f"Every image is converted to gray in [0, 1] and area-resized to {size[0]}x{size[1]} "
        "(HxW). Methods are fitted on the reference traverse only. Score matrices have one row "
        "per query; a query's prediction is its highest-scoring reference. Precision-recall: "
        "queries ranked by that score; a prediction is correct when within the tolerance; "
        "recall counts the matchable queries (those with a reference within the tolerance), "
        "so a query without one lowers precision only. AUC is the area under that curve; R@1 "
        "the share of matchable queries whose best match is correct; R@100%P the largest "
        "recall at precision 1."
    )


_MACHINE_KEYS = ["cpu", "cores", "usable_cores", "platform", "python", "numpy", "torch", "flyvpr"]
_SESSION_COLUMNS = {
    "started": "started",
    "finished": "finished",
    "backend": "backend",
    "n_jobs": "jobs",
    "n_runs": "runs",
    "n_skipped": "skipped (done before)",
    "n_ran": "ran",
    "n_errors": "failed",
}


def _machines_section(doc: Document, records: dict, sessions: list[dict]) -> None:
    doc.heading(2, "Protocol: machines", anchor="machines")
    # One row per machine; torch's version is known only for runs that loaded it.
    machines: dict[str, dict] = {}
    for rec in records.values():
        m = rec.get("machine")
        if not m:
            continue
        key = json.dumps({k: v for k, v in m.items() if k != "torch"}, sort_keys=True)
        row = machines.setdefault(key, {**m, "runs": 0})
        row["runs"] += 1
        if m.get("torch"):
            row["torch"] = m["torch"]
    if not machines:
        for session in sessions:
            m = session.get("machine")
            if m:
                machines.setdefault(json.dumps(m, sort_keys=True), {**m, "runs": 0})
    keys = [*_MACHINE_KEYS, "runs"]
    doc.table(
        keys,
        [[m.get(k, "-") for k in keys] for m in machines.values()],
        "machines the runs executed on",
    )
    doc.table(
        list(_SESSION_COLUMNS.values()),
        [
            [s.get(k, "(interrupted)" if k == "finished" else "-") for k in _SESSION_COLUMNS]
            for s in sessions
        ],
        "sessions of `flyvpr experiment` into this folder",
    )


def build_report(results_dir, figures: bool = True) -> Document:
    """The report of a results folder as blocks, without writing anything.

    Parameters
    ----------
    results_dir : str or Path
        The ``--out`` folder of ``flyvpr experiment``.
    figures : bool
        Draw the figures (needs matplotlib, the ``plot`` extra).

    Returns
    -------
    Document
        Its ``blocks`` hold the report's headings, paragraphs, lists and tables
        (``docs/generate_results.py`` keeps them as the paper page's data);
        ``html()`` and ``markdown()`` render it.

    Raises
    ------
    FileNotFoundError, ValueError
        As :func:`load_results`.
    ImportError
        If ``figures`` is true and matplotlib is not installed.
    """
    if figures:
        from .plots import require_matplotlib

        require_matplotlib()
    config, experiment, records = load_results(results_dir)
    return _build(config, experiment, records, figures)


def write_report(results_dir, figures: bool = True) -> tuple[Path, Path]:
    """Write ``report.html`` (self-contained) and ``report.md`` into a results folder.

    Parameters
    ----------
    results_dir : str or Path
        The ``--out`` folder of ``flyvpr experiment``.
    figures : bool
        Draw the figures (needs matplotlib, the ``plot`` extra); ``False``
        writes tables and text only.

    Returns
    -------
    (Path, Path)
        The HTML and Markdown files.

    Raises
    ------
    FileNotFoundError
        If ``results_dir`` or its ``experiment.json`` is missing.
    ImportError
        If ``figures`` is true and matplotlib is not installed (the message
        names ``pip install 'flyvpr[plot]'``).
    """
    results_dir = Path(results_dir)
    doc = build_report(results_dir, figures)
    fig_dir = results_dir / "figures"
    if doc.figures:
        fig_dir.mkdir(exist_ok=True)
        for name, png in doc.figures.items():
            write_bytes_atomic(fig_dir / f"{name}.png", png)
    html_path = write_text_atomic(results_dir / "report.html", doc.html())
    md_path = write_text_atomic(results_dir / "report.md", doc.markdown("figures"))
    logger.info("wrote %s and %s (%d figures)", html_path, md_path, len(doc.figures))
    return html_path, md_path
