"""Turn an experiment's run files into ``report.html`` and ``report.md``.

``DIR/report.html`` is self-contained (figures embedded as base64 PNG); it
holds one section per grid of the config (tables and figures by the grid's
kind), the protocol of every number (data, frame range, reference and query
roles, tolerance, image size, seeds, parameters) and the machines the runs
used.  ``DIR/report.md`` holds the same text and tables, with the figures as
PNG files in ``DIR/figures/``.

Aggregates are over seeds: mean ± sample standard deviation (n - 1) and the
number of runs.  AUC, Recall@1, recall at 100% precision and training
accuracy are shown in percent.  Precision-recall curves and qualitative
examples show the grid's first seed.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .._io import write_text_atomic
from .config import ExperimentConfig, GridBlock, RunSpec, parse_config
from .runner import load_run

__all__ = ["write_report", "load_results"]

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
        run id -> run record, for every readable file in ``runs/``.

    Raises
    ------
    FileNotFoundError
        If the folder or its ``experiment.json`` is missing.
    """
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise FileNotFoundError(f"results folder not found: {results_dir}")
    exp_file = results_dir / "experiment.json"
    experiment = load_run(exp_file)
    if experiment is None:
        raise FileNotFoundError(
            f"{exp_file} is missing or unreadable: is {results_dir} the --out folder of "
            "`flyvpr experiment`?"
        )
    stored = experiment["config"]
    config = parse_config(
        experiment["config_text"],
        base_dir=stored["base_dir"],
        source=experiment.get("config_path", "config"),
        path=stored.get("path"),
    )
    records = {}
    for path in sorted((results_dir / "runs").glob("*.json")):
        record = load_run(path)
        if record is not None and "run_id" in record:
            records[record["run_id"]] = record
    return config, experiment, records


# -- small helpers -------------------------------------------------------------------------------
def _stats(values) -> tuple[float, float, int]:
    vals = np.array([v for v in values if v is not None], dtype=float)
    if vals.size == 0:
        return math.nan, math.nan, 0
    sd = float(vals.std(ddof=1)) if vals.size > 1 else 0.0
    return float(vals.mean()), sd, int(vals.size)


def _pct(stat, digits: int = 1) -> str:
    mean, sd, n = stat
    if n == 0 or not math.isfinite(mean):
        return "-"
    if n == 1:
        return f"{100 * mean:.{digits}f}"
    return f"{100 * mean:.{digits}f} ± {100 * sd:.{digits}f}"


def _num(value, fmt: str = ".3g") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, fmt)


def _combo_label(combo: dict, axes: list[str]) -> str:
    return ", ".join(f"{k}={combo[k]}" for k in axes)


def _tolerance_text(tol) -> str:
    if isinstance(tol, dict) and tol:
        return ", ".join(f"{v} {k}" for k, v in tol.items())
    return "-" if tol is None else str(tol)


class _Doc:
    """Blocks of a report, rendered to HTML and to Markdown."""

    def __init__(self):
        self.blocks: list[tuple] = []
        self.figures: dict[str, bytes] = {}

    def heading(self, level: int, text: str, anchor: str | None = None):
        self.blocks.append(("h", level, text, anchor))

    def para(self, text: str, cls: str | None = None):
        self.blocks.append(("p", text, cls))

    def items(self, entries: list):
        """A bullet list; an entry is a str or a (text, anchor) pair (a link in HTML)."""
        self.blocks.append(("ul", entries))

    def table(self, headers: list[str], rows: list[list[str]], caption: str = ""):
        self.blocks.append(("table", headers, rows, caption))

    def figure(self, name: str, png: bytes, caption: str):
        self.figures[name] = png
        self.blocks.append(("fig", name, caption))

    def code(self, text: str):
        self.blocks.append(("pre", text))

    # rendering
    def html(self, title: str) -> str:
        esc = html.escape
        out = [
            "<!DOCTYPE html>",
            '<html lang="en"><head><meta charset="utf-8">',
            '<meta name="viewport" content="width=device-width, initial-scale=1">',
            f"<title>{esc(title)}</title>",
            f"<style>{_CSS}</style>",
            "</head><body><main>",
        ]
        for block in self.blocks:
            kind = block[0]
            if kind == "h":
                _, level, text, anchor = block
                ident = f' id="{esc(anchor)}"' if anchor else ""
                out.append(f"<h{level}{ident}>{esc(text)}</h{level}>")
            elif kind == "p":
                _, text, cls = block
                attr = f' class="{cls}"' if cls else ""
                out.append(f"<p{attr}>{esc(text)}</p>")
            elif kind == "ul":
                lis = []
                for entry in block[1]:
                    if isinstance(entry, tuple):
                        lis.append(f'<li><a href="#{esc(entry[1])}">{esc(entry[0])}</a></li>')
                    else:
                        lis.append(f"<li>{esc(entry)}</li>")
                out.append("<ul>" + "".join(lis) + "</ul>")
            elif kind == "table":
                _, headers, rows, caption = block
                out.append("<table>")
                if caption:
                    out.append(f"<caption>{esc(caption)}</caption>")
                out.append("<thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in headers))
                out.append("</tr></thead><tbody>")
                for row in rows:
                    out.append("<tr>" + "".join(f"<td>{esc(str(c))}</td>" for c in row) + "</tr>")
                out.append("</tbody></table>")
            elif kind == "fig":
                _, name, caption = block
                data = base64.b64encode(self.figures[name]).decode("ascii")
                out.append(
                    f'<figure><img src="data:image/png;base64,{data}" alt="{esc(caption)}">'
                    f"<figcaption>{esc(caption)}</figcaption></figure>"
                )
            elif kind == "pre":
                out.append(f"<pre>{esc(block[1])}</pre>")
        out.append("</main></body></html>")
        return "\n".join(out) + "\n"

    def markdown(self, figure_dir: str) -> str:
        out = []

        def cell(text) -> str:
            return str(text).replace("|", "\\|").replace("\n", " ")

        for block in self.blocks:
            kind = block[0]
            if kind == "h":
                out.append("#" * block[1] + " " + block[2])
            elif kind == "p":
                out.append(block[1])
            elif kind == "ul":
                out.append("\n".join(f"- {t[0] if isinstance(t, tuple) else t}" for t in block[1]))
            elif kind == "table":
                _, headers, rows, caption = block
                lines = []
                if caption:
                    lines.append(f"*{caption}*\n")
                lines.append("| " + " | ".join(cell(h) for h in headers) + " |")
                lines.append("|" + "|".join("---" for _ in headers) + "|")
                lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
                out.append("\n".join(lines))
            elif kind == "fig":
                _, name, caption = block
                out.append(f"![{name}]({figure_dir}/{name}.png)\n\n*{caption}*")
            elif kind == "pre":
                out.append("```\n" + block[1] + "\n```")
        return "\n\n".join(out) + "\n"


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;
color:#1b1b1b;background:#fff;margin:0}
main{max-width:1100px;margin:0 auto;padding:1.5rem 2rem 4rem}
h1{font-size:1.7rem;margin-bottom:.2rem}h2{margin-top:2.4rem;border-bottom:1px solid #ccc;
padding-bottom:.2rem}h3{margin-top:1.6rem}
table{border-collapse:collapse;margin:.8rem 0 1.2rem;font-size:.85rem}
caption{text-align:left;font-style:italic;padding-bottom:.3rem;color:#444}
th,td{border:1px solid #ccc;padding:.25rem .55rem;text-align:left;vertical-align:top}
th{background:#f0f2f5}tbody tr:nth-child(even){background:#fafafa}
figure{margin:1rem 0 1.6rem}figure img{max-width:100%;height:auto;border:1px solid #ddd}
figcaption{font-size:.85rem;color:#444;margin-top:.3rem}
pre{background:#f6f8fa;padding:.6rem;overflow-x:auto;font-size:.8rem}
.protocol{font-size:.85rem;color:#333;background:#f6f8fa;padding:.5rem .7rem;
border-left:3px solid #7a9cc6}.error{color:#b00020}.muted{color:#666;font-size:.85rem}
"""


# -- entries of a grid ---------------------------------------------------------------------------
class _Grid:
    """A grid's runs joined with their records."""

    def __init__(self, config: ExperimentConfig, grid: GridBlock, records: dict, plan: list | None):
        self.grid = grid
        self.config = config
        self.axes = grid.axes
        if plan is None:  # an experiment.json without a plan: expand the grid now
            plan = [
                {k: item[k] for k in ("dataset", "method", "seed", "combo")}
                | {"run_id": item["run"].run_id}
                for item in config.grid_items(grid)
            ]
        self.items = [{**item, "record": records.get(item["run_id"])} for item in plan]

    def run_spec(self, item: dict) -> RunSpec:
        """The :class:`RunSpec` of a finished run (to reload its benchmark)."""
        return RunSpec(
            item["run_id"],
            item["record"]["spec"],
            dict(self.config.datasets[item["dataset"]].resolved),
            cache=self.config.settings.cache,
        )

    @property
    def ok(self) -> list[dict]:
        return [i for i in self.items if i["record"] and i["record"].get("status") == "ok"]

    def groups(self) -> list[tuple[tuple, list[dict]]]:
        """Finished runs grouped by (dataset, method, axis values), in grid order."""
        out: dict[tuple, list[dict]] = {}
        for item in self.ok:
            key = (
                item["dataset"],
                item["method"],
                tuple(json.dumps(item["combo"][a]) for a in self.axes),
            )
            out.setdefault(key, []).append(item)
        return list(out.items())

    def label(self, item: dict) -> str:
        extra = _combo_label(item["combo"], self.axes)
        return f"{item['method']} ({extra})" if extra else item["method"]

    def dataset_label(self, name: str) -> str:
        return self.config.datasets[name].label

    def first_seed_items(self) -> list[dict]:
        """Per group, the finished run with the lowest seed listed first in the grid."""

        def position(item):
            return self.grid.seeds_for(item["method"]).index(item["seed"])

        return [min(items, key=position) for _, items in self.groups()]


def _protocol_line(g: _Grid, records_protocols: dict) -> str:
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
    n_ref = proto.get("n_reference")
    rng = proto.get("frame_number_range")
    frames = f"positions {first}..{first + n_ref - 1}" if n_ref else "all frames"
    if rng:
        frames += f" (file frames {rng[0]}..{rng[1]})"
    text = (
        f"{proto.get('dataset')} reference={proto.get('reference')} query={proto.get('query')}, "
        f"{frames}, {n_ref} references x {proto.get('n_query')} queries, "
        f"tolerance {_tolerance_text(proto.get('tolerance'))}"
    )
    if proto.get("query_subset"):
        text += f", {proto['query_subset']}"
    return text


# -- sections by kind ----------------------------------------------------------------------------
def _metric_table(doc: _Doc, g: _Grid) -> None:
    headers = (
        ["condition", "method"]
        + g.axes
        + [
            "AUC (%)",
            "R@1 (%)",
            "R@100%P (%)",
            "train acc (%)",
            "seeds",
        ]
    )
    rows = []
    for (ds, method, _), items in g.groups():
        res = [i["record"]["result"] for i in items]
        rows.append(
            [g.dataset_label(ds), method]
            + [str(items[0]["combo"][a]) for a in g.axes]
            + [
                _pct(_stats(r["auc"] for r in res)),
                _pct(_stats(r["recall_at_1"] for r in res)),
                _pct(_stats(r["recall_at_100_precision"] for r in res)),
                _pct(_stats(r.get("train_accuracy") for r in res)),
                str(len(res)),
            ]
        )
    doc.table(
        headers,
        rows,
        "mean ± sd over seeds (sd shown when more than one seed); train acc: on the reference "
        "traverse. Runs share the CPU here, so times are reported by timing grids only.",
    )


def _section_evaluate(doc: _Doc, g: _Grid, figures: bool, order: list[str]) -> None:
    _metric_table(doc, g)
    if not figures or not g.ok:
        return
    from . import plots

    labels: list[str] = []
    for _, items in g.groups():
        label = g.label(items[0])
        if label not in labels:
            labels.append(label)
    series = []
    for ds in g.grid.datasets:
        mean, sd, n = [], [], []
        for label in labels:
            res = [
                i["record"]["result"]["auc"]
                for _, items in g.groups()
                for i in items
                if i["dataset"] == ds and g.label(i) == label
            ]
            m, s, k = _stats(res)
            mean.append(100 * m)
            sd.append(100 * s)
            n.append(k)
        series.append({"label": g.dataset_label(ds), "mean": mean, "sd": sd, "n": n})
    name = f"{g.grid.name}_auc"
    doc.figure(
        name,
        plots.auc_bars(labels, series, g.grid.title),
        f"{g.grid.title}: area under the precision-recall curve (%), mean ± sd over seeds.",
    )
    panels = []
    for ds in g.grid.datasets:
        curves = []
        for item in g.first_seed_items():
            if item["dataset"] != ds:
                continue
            res = item["record"]["result"]
            curves.append(
                {
                    "label": g.label(item) + f", seed {item['seed']}",
                    "key": item["method"],
                    "recall": res["recall"],
                    "precision": res["precision"],
                    "auc": 100 * res["auc"],
                }
            )
        panels.append({"title": g.dataset_label(ds), "curves": curves})
    doc.figure(
        f"{g.grid.name}_pr",
        plots.pr_curves(panels, order),
        f"{g.grid.title}: precision-recall curves per condition (queries ranked by the score "
        "of their best match; a query is correct when that match lies within the tolerance).",
    )


def _section_sensitivity(doc: _Doc, g: _Grid, figures: bool, order: list[str]) -> None:
    _metric_table(doc, g)
    if not figures or not g.ok:
        return
    from . import plots

    axis = g.axes[0]
    values = g.grid.params[axis]
    series = []
    for ds in g.grid.datasets:
        for method in g.grid.methods:
            acc_m, acc_s, auc_m, auc_s = [], [], [], []
            for v in values:
                res = [
                    i["record"]["result"]
                    for i in g.ok
                    if i["dataset"] == ds and i["method"] == method and i["combo"][axis] == v
                ]
                a = _stats(r.get("train_accuracy") for r in res)
                u = _stats(r["auc"] for r in res)
                acc_m.append(100 * a[0])
                acc_s.append(100 * a[1])
                auc_m.append(100 * u[0])
                auc_s.append(100 * u[1])
            label = f"{method}, {g.dataset_label(ds)}"
            series.append(
                {
                    "label": label,
                    "key": method,
                    "x": values,
                    "acc_mean": acc_m,
                    "acc_sd": acc_s,
                    "auc_mean": auc_m,
                    "auc_sd": auc_s,
                }
            )
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    if not numeric:
        doc.para(f"{axis} is not numeric: no sensitivity plot.", "muted")
        return
    percent = all(0 <= v <= 1 for v in values)
    doc.figure(
        f"{g.grid.name}_sensitivity",
        plots.sensitivity(axis, series, order, percent),
        f"{g.grid.title}: training accuracy on the reference traverse and AUC on the queries "
        f"against {axis}; mean ± sd over seeds.",
    )


def _section_training(doc: _Doc, g: _Grid, figures: bool, order: list[str]) -> None:
    rows = []
    panels = []
    for ds in g.grid.datasets:
        series = []
        for (d, method, _), items in g.groups():
            if d != ds:
                continue
            res = [i["record"]["result"] for i in items]
            histories = [r["accuracy_history"] for r in res]
            n_epochs = min(len(h) for h in histories)
            curves = np.array([h[:n_epochs] for h in histories], dtype=float)
            final = _stats(r.get("train_accuracy") for r in res)
            best_epoch = int(np.argmax(curves.mean(axis=0))) + 1
            rows.append(
                [
                    g.dataset_label(ds),
                    g.label(items[0]),
                    str(n_epochs),
                    _pct(final),
                    str(best_epoch),
                    _num(_stats(r["fit_s"] for r in res)[0], ".2f"),
                    str(len(res)),
                ]
            )
            sd = curves.std(axis=0, ddof=1) if len(curves) > 1 else np.zeros(n_epochs)
            series.append(
                {
                    "label": g.label(items[0]),
                    "key": method,
                    "mean": 100 * curves.mean(axis=0),
                    "sd": 100 * sd,
                    "n": len(res),
                }
            )
        panels.append(
            {"title": f"training on {g.dataset_label(ds)} (reference traverse)", "series": series}
        )
    doc.table(
        [
            "condition",
            "method",
            "epochs",
            "final train acc (%)",
            "epoch of best mean acc",
            "fit (s)",
            "seeds",
        ],
        rows,
        "training accuracy on the reference traverse (one class per place), mean ± sd over seeds",
    )
    if figures and g.ok:
        from . import plots

        doc.figure(
            f"{g.grid.name}_training",
            plots.training_curves(panels, order),
            f"{g.grid.title}: training accuracy per epoch, mean (line) ± 1 sd (band) over seeds.",
        )


def _section_timing(doc: _Doc, g: _Grid, figures: bool, order: list[str]) -> None:
    rows = []
    for (ds, _method, _), items in g.groups():
        t = [i["record"]["result"]["timing"] for i in items]
        res = [i["record"]["result"] for i in items]
        n_q = res[0]["n_query"]
        n_r = res[0]["n_reference"]
        extraction = _stats(x.get("load_query_s", 0.0) + x["encode_s"] for x in t)[0]
        matching = _stats(x["match_s"] for x in t)[0]
        per_query = (extraction + matching) / n_q
        rows.append(
            [
                g.dataset_label(ds),
                g.label(items[0]),
                f"{n_q} x {n_r}",
                f"{extraction:.2f}",
                f"{matching:.2f}",
                f"{per_query:.4f} ({1 / per_query:.1f})" if per_query > 0 else "-",
                _num(_stats(x["fit_s"] for x in t)[0], ".2f"),
                _num(_stats(x.get("load_reference_s") for x in t)[0], ".2f"),
                str(len(t)),
            ]
        )
    doc.table(
        [
            "condition",
            "method",
            "queries x references",
            "feature extraction (s)",
            "place matching (s)",
            "per query (s) (fps)",
            "training (s)",
            "reference decoding (s)",
            "runs",
        ],
        rows,
        "feature extraction = decoding and resizing the query images (no cache) + encoding "
        "them; place matching = scoring against every reference + temporal filtering; per "
        "query = (extraction + matching) / queries. Runs executed one at a time after a "
        "warm-up; mean over seeds.",
    )
    doc.para(
        "For comparison, the paper (different hardware, full-resolution frames) reports for "
        "1000 Nordland queries against 1000 references: FlyNet+CANN 35 s extraction, 25 s "
        "matching, 0.06 s per query (16.66 fps); SeqSLAM 50 s, 40 s, 0.09 s (11.11 fps).",
        "muted",
    )


def _section_footprint(doc: _Doc, g: _Grid, figures: bool, order: list[str]) -> None:
    rows = []
    panels = []
    for ds in g.grid.datasets:
        points = []
        for (d, _method, _), items in g.groups():
            if d != ds:
                continue
            res = [i["record"]["result"] for i in items]
            fp = res[0]["footprint"]
            auc = _stats(r["auc"] for r in res)
            rows.append(
                [
                    g.dataset_label(ds),
                    g.label(items[0]),
                    str(fp["layers"]),
                    f"{fp['params']:,}",
                    f"{fp['neurons']:,}",
                    f"{res[0]['model_bytes']:,}" if res[0].get("model_bytes") else "-",
                    _pct(auc),
                    str(len(res)),
                ]
            )
            if int(fp["params"]) <= 0:
                continue  # nothing trained: no place on a log axis (listed in the table)
            points.append(
                {
                    "label": g.label(items[0]),
                    "key": items[0]["method"],
                    "params": max(int(fp["params"]), 1),
                    "auc": 100 * auc[0],
                    "auc_sd": 100 * auc[1],
                    "layers": int(fp["layers"]),
                }
            )
        panels.append({"title": g.dataset_label(ds), "points": points})
    doc.table(
        [
            "condition",
            "method",
            "layers",
            "trained params",
            "neurons",
            "bytes on disk",
            "AUC (%)",
            "seeds",
        ],
        rows,
        "footprint as in the paper's table: layers, trained parameters (fixed random "
        "connections excluded) and neurons, for the number of reference places of each "
        "condition; bytes on disk of the saved model file (flyvpr fit --save; FlyHash "
        "connections bit-packed; pixels/SeqSLAM store the patch-normalised reference images)",
    )
    doc.para(
        "The paper's table (1000 places): FlyNet 2 layers / 64k params / 1064 neurons, "
        "FlyNet+RNN 4 / 1.3m / 2576, FlyNet+CANN 3 / 72k / 2066. flyvpr counts FlyNet exactly "
        "as the paper (64 x 1000 trained output weights; the FNA's fixed binary connections "
        "are not parameters) and FlyNet+RNN within rounding (torch's two bias vectors per "
        "recurrent block included). For the CANN flyvpr counts its connections (local "
        "excitation over 7 neighbours per unit plus the links to and from the global "
        "inhibitor, about 9k for 1000 places) and 1001 units (places + inhibitor): 3 layers, "
        "73k, 2065 neurons; the paper's 72k/2066 imply about 8k CANN weights and 1002 units, "
        "which its text does not break down.",
        "muted",
    )
    if figures and g.ok:
        from . import plots

        doc.figure(
            f"{g.grid.name}_size",
            plots.auc_vs_size(panels, order),
            f"{g.grid.title}: AUC (mean ± sd over seeds) against trained parameters (log "
            "scale); marker area proportional to the number of layers; methods without trained "
            "parameters appear in the table only.",
        )


def _section_qualitative(doc: _Doc, g: _Grid, figures: bool, order: list[str]) -> None:
    from .runner import _benchmark

    rows = []
    for ds in g.grid.datasets:
        items = [i for i in g.first_seed_items() if i["dataset"] == ds]
        if not items:
            continue
        n_query = len(items[0]["record"]["predictions"])
        if g.grid.queries is not None:
            queries = [q for q in g.grid.queries if q < n_query]
        else:
            queries = np.linspace(0, n_query - 1, g.grid.examples + 2)[1:-1].round().astype(int)
            queries = sorted(set(int(q) for q in queries))
        for item in items:
            rec = item["record"]
            rows.append(
                [g.dataset_label(ds), g.label(item), str(item["seed"])]
                + [
                    f"q{q}->r{rec['predictions'][q]} {'ok' if rec['correct'][q] else 'wrong'}"
                    for q in queries
                ]
            )
        if not figures:
            continue
        try:
            bench = _benchmark(g.run_spec(items[0]))
            fig_rows = _qualitative_rows(bench, items, queries, g)
        except (OSError, ValueError) as exc:
            doc.para(f"{g.dataset_label(ds)}: no thumbnails ({exc}).", "error")
            continue
        from . import plots

        doc.figure(
            f"{g.grid.name}_{ds}_examples",
            plots.qualitative(fig_rows, [g.label(i) for i in items], g.dataset_label(ds)),
            f"{g.grid.title}, {g.dataset_label(ds)}: query frames (left), the true reference "
            "place and the reference each method retrieved (its best match), framed green "
            f"when within the tolerance and red otherwise; seed {items[0]['seed']}; images as "
            "the methods see them.",
        )
    if rows:
        width = max(len(r) for r in rows) - 3
        doc.table(
            ["condition", "method", "seed"] + [f"example {k + 1}" for k in range(width)],
            rows,
            "query position -> retrieved reference position",
        )


def _qualitative_rows(bench, items, queries, g: _Grid) -> list[dict]:
    from ..images import load_image

    size = tuple(items[0]["record"]["spec"]["image_size"])
    ref_paths, qry_paths = bench.reference.paths, bench.query.paths
    cache: dict = {}

    def ref_image(j):
        if j not in cache:
            cache[j] = load_image(ref_paths[j], size, bayer=bench.reference.bayer)
        return cache[j]

    rows = []
    gt = bench.ground_truth
    for q in queries:
        true = np.flatnonzero(gt[q])
        truth = int(true[len(true) // 2]) if true.size else None
        retrieved = []
        for item in items:
            j = int(item["record"]["predictions"][q])
            retrieved.append(
                {"image": ref_image(j), "label": f"ref {j}", "correct": bool(gt[q, j])}
            )
        rows.append(
            {
                "query": load_image(qry_paths[q], size, bayer=bench.query.bayer),
                "query_label": f"query {q}",
                "truth": None if truth is None else ref_image(truth),
                "truth_label": "no match" if truth is None else f"ref {truth}",
                "retrieved": retrieved,
            }
        )
    return rows


_SECTIONS = {
    "evaluate": _section_evaluate,
    "sensitivity": _section_sensitivity,
    "training_curve": _section_training,
    "timing": _section_timing,
    "footprint": _section_footprint,
    "qualitative": _section_qualitative,
}


# -- the report ----------------------------------------------------------------------------------
def _build(config: ExperimentConfig, experiment: dict, records: dict, figures: bool) -> _Doc:
    from .. import __version__

    doc = _Doc()
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
    else:
        plan = {}
        all_ids = {r.run_id for r in config.runs()}
    mine = {k: v for k, v in records.items() if k in all_ids}
    n_ok = sum(1 for r in mine.values() if r.get("status") == "ok")
    n_err = sum(1 for r in mine.values() if r.get("status") != "ok")
    n_missing = len(all_ids) - len(mine)
    stale = len(records) - len(mine)
    summary = f"{len(all_ids)} distinct runs: {n_ok} finished, {n_err} failed, {n_missing} not run."
    if stale:
        summary += f" {stale} run file(s) in runs/ belong to no grid of this config (ignored)."
    doc.para(summary)

    grids = [_Grid(config, grid, records, plan.get(grid.name)) for grid in config.grids]
    doc.heading(2, "Contents")
    doc.items(
        [(f"{grid.title} ({grid.kind})", f"grid-{grid.name}") for grid in config.grids]
        + [
            ("Protocol: data", "data"),
            ("Protocol: machines", "machines"),
            ("Failed runs", "errors"),
        ]
    )

    order: list[str] = []
    for grid in config.grids:
        order += [m for m in grid.methods if m not in order]

    protocols: dict[str, dict] = {}
    for g in grids:
        for item in g.ok:
            protocols.setdefault(item["dataset"], item["record"].get("protocol"))

    for g in grids:
        doc.heading(2, g.grid.title, anchor=f"grid-{g.grid.name}")
        if g.grid.description:
            doc.para(g.grid.description)
        doc.para(_protocol_line(g, protocols), "protocol")
        if not g.ok:
            doc.para("No finished run in this grid yet.", "error")
            continue
        _SECTIONS[g.grid.kind](doc, g, figures, order)

    doc.heading(2, "Protocol: data", anchor="data")
    rows = []
    for name, ds in config.datasets.items():
        proto = protocols.get(name)
        rows.append(
            [
                name,
                ds.label,
                ds.loader,
                str(ds.options.get("root", "")),
                _dataset_protocol_text(ds, proto),
            ]
        )
    doc.table(["dataset", "label", "loader", "root (as configured)", "protocol"], rows)
    size = config.settings.image_size
    doc.para(
        f"Every image is converted to gray in [0, 1] and area-resized to {size[0]}x{size[1]} "
        "(HxW). Methods are fitted on the reference traverse only. Score matrices have one row "
        "per query; a query's prediction is its highest-scoring reference. Precision-recall: "
        "queries ranked by that score; a prediction is correct when within the tolerance. "
        "AUC is the area under that curve; R@1 the share of queries whose best match is "
        "correct; R@100%P the largest recall at precision 1."
    )

    doc.heading(2, "Protocol: machines", anchor="machines")
    # One row per machine; torch's version is known only for runs that loaded it.
    machines: dict[str, dict] = {}
    for rec in mine.values():
        m = rec.get("machine")
        if not m:
            continue
        key = json.dumps({k: v for k, v in m.items() if k != "torch"}, sort_keys=True)
        row = machines.setdefault(key, {**m, "runs": 0})
        row["runs"] += 1
        if m.get("torch"):
            row["torch"] = m["torch"]
    if not machines:
        for session in experiment.get("sessions", []):
            m = session.get("machine")
            if m:
                machines.setdefault(json.dumps(m, sort_keys=True), {**m, "runs": 0})
    keys = [
        "cpu",
        "cores",
        "usable_cores",
        "platform",
        "python",
        "numpy",
        "torch",
        "flyvpr",
        "runs",
    ]
    doc.table(
        keys,
        [[str(m.get(k, "-")) for k in keys] for m in machines.values()],
        "machines the runs executed on",
    )
    doc.table(
        [
            "started",
            "finished",
            "backend",
            "jobs",
            "runs",
            "skipped (done before)",
            "ran",
            "failed",
        ],
        [
            [
                s.get("started", "-"),
                s.get("finished", "(interrupted)"),
                s.get("backend", "-"),
                str(s.get("n_jobs", "-")),
                str(s.get("n_runs", "-")),
                str(s.get("n_skipped", "-")),
                str(s.get("n_ran", "-")),
                str(s.get("n_errors", "-")),
            ]
            for s in experiment.get("sessions", [])
        ],
        "sessions of `flyvpr experiment` into this folder",
    )

    doc.heading(2, "Failed runs", anchor="errors")
    failed = [r for r in mine.values() if r.get("status") != "ok"]
    if failed:
        doc.table(["run", "error"], [[r["run_id"], r.get("error", "?")] for r in failed])
    else:
        doc.para("None.")
    doc.heading(2, "Configuration")
    doc.code(config.text.strip())
    return doc


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
    if figures:
        from .plots import require_matplotlib

        require_matplotlib()
    results_dir = Path(results_dir)
    config, experiment, records = load_results(results_dir)
    doc = _build(config, experiment, records, figures)
    fig_dir = results_dir / "figures"
    if doc.figures:
        fig_dir.mkdir(exist_ok=True)
        for name, png in doc.figures.items():
            _write_bytes_atomic(fig_dir / f"{name}.png", png)
    html_path = write_text_atomic(results_dir / "report.html", doc.html(config.title))
    md_path = write_text_atomic(results_dir / "report.md", doc.markdown("figures"))
    logger.info("wrote %s and %s (%d figures)", html_path, md_path, len(doc.figures))
    return html_path, md_path


def _write_bytes_atomic(path: Path, data: bytes) -> None:
    from .._io import write_bytes_atomic

    write_bytes_atomic(path, data)
