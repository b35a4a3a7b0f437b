"""The report's section of each kind of grid: tables and figures from a grid's finished runs.

A section reads the runs of one grid (:class:`GridRuns`: the grid's plan joined
with the run records) and adds blocks to a
:class:`~flyvpr.experiments.document.Document`: a table of the numbers and,
when figures are asked for, the plots of :mod:`flyvpr.experiments.plots`.

Aggregates are over seeds: mean ± sample standard deviation (n - 1) and the
number of runs.  AUC, Recall@1, recall at 100% precision and training
accuracy are shown in percent.  Precision-recall curves and qualitative
examples show the grid's first seed.
"""

from __future__ import annotations

import json
import math

import numpy as np

from .config import ExperimentConfig, GridBlock
from .document import Document
from .runs import RunSpec, load_benchmark_of

__all__ = ["GridRuns", "SECTIONS"]


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


# -- entries of a grid ---------------------------------------------------------------------------
class GridRuns:
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
        """A finished run's :class:`~flyvpr.experiments.runs.RunSpec` (to reload its data)."""
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


# -- sections by kind ----------------------------------------------------------------------------
def _metric_table(doc: Document, g: GridRuns) -> None:
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


def _section_evaluate(doc: Document, g: GridRuns, figures: bool, order: list[str]) -> None:
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


def _section_sensitivity(doc: Document, g: GridRuns, figures: bool, order: list[str]) -> None:
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


def _section_training(doc: Document, g: GridRuns, figures: bool, order: list[str]) -> None:
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


def _section_timing(doc: Document, g: GridRuns, figures: bool, order: list[str]) -> None:
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
        "query = (extraction + matching) / queries. Runs executed one at a time "
        + (
            "after a warm-up (the method run untimed on 100 frames first)"
            if g.grid.warmup
            else "without a warm-up (warmup = false: the first run of a method pays its "
            "compilation and first-call costs)"
        )
        + "; mean over seeds.",
    )
    doc.para(
        "For comparison, the paper (different hardware, full-resolution frames) reports for "
        "1000 Nordland queries against 1000 references: FlyNet+CANN 35 s extraction, 25 s "
        "matching, 0.06 s per query (16.66 fps); SeqSLAM 50 s, 40 s, 0.09 s (11.11 fps).",
        "muted",
    )


def _section_footprint(doc: Document, g: GridRuns, figures: bool, order: list[str]) -> None:
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


def _section_qualitative(doc: Document, g: GridRuns, figures: bool, order: list[str]) -> None:
    rows = []
    for ds in g.grid.datasets:
        items = [i for i in g.first_seed_items() if i["dataset"] == ds]
        if not items:
            continue
        n_query = len(items[0]["record"]["predictions"])
        if g.grid.queries is not None:
            queries = [q for q in g.grid.queries if q < n_query]
            beyond = [q for q in g.grid.queries if q >= n_query]
            if beyond:  # (the runner refuses them; run files from elsewhere may have fewer)
                doc.para(
                    f"{g.dataset_label(ds)}: queries {', '.join(map(str, beyond))} lie beyond "
                    f"its {n_query} queries: not shown.",
                    "error",
                )
        else:
            spread = np.linspace(0, n_query - 1, g.grid.examples + 2)[1:-1].round().astype(int)
            queries = sorted(set(int(q) for q in spread))
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
            bench = load_benchmark_of(g.run_spec(items[0]))
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


def _qualitative_rows(bench, items, queries, g: GridRuns) -> list[dict]:
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


SECTIONS = {
    "evaluate": _section_evaluate,
    "sensitivity": _section_sensitivity,
    "training_curve": _section_training,
    "timing": _section_timing,
    "footprint": _section_footprint,
    "qualitative": _section_qualitative,
}
