"""Figures of the experiment report, drawn with matplotlib (the optional ``plot`` extra).

Every function takes plain numbers (lists, arrays, dicts) and returns the
figure as PNG bytes.  Figures are built on :class:`matplotlib.figure.Figure`
directly, with the Agg renderer and without pyplot, so drawing a report
changes no global matplotlib state and needs no display.  matplotlib is
imported inside the functions: importing this module costs nothing.
"""

from __future__ import annotations

import io
import math

import numpy as np

__all__ = [
    "require_matplotlib",
    "auc_bars",
    "pr_curves",
    "sensitivity",
    "training_curves",
    "auc_vs_size",
    "qualitative",
]

#: dots per inch of the saved PNGs (a 10-inch figure is 1000 pixels wide)
DPI = 100


def require_matplotlib():
    """Import matplotlib or raise an ImportError that names the extra to install."""
    try:
        import matplotlib
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise ImportError(
            "report figures need matplotlib: pip install 'flyvpr[plot]' "
            "(or write the report without figures)"
        ) from exc
    return matplotlib, Figure


def _figure(width: float, height: float):
    _, Figure = require_matplotlib()
    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _colour(key: str, order: list[str]):
    """A stable colour per method: its position in ``order`` in the tab10/tab20 cycle."""
    matplotlib, _ = require_matplotlib()
    cmap = matplotlib.colormaps["tab10" if len(order) <= 10 else "tab20"]
    index = order.index(key) if key in order else len(order)
    return cmap(index % cmap.N)


def _grid(n: int, max_cols: int = 2) -> tuple[int, int]:
    cols = min(n, max_cols)
    return math.ceil(n / cols), cols


def auc_bars(groups: list[str], series: list[dict], title: str, ylabel: str = "AUC (%)") -> bytes:
    """Grouped bars: one group per entry of ``groups``, one bar per series.

    Parameters
    ----------
    groups : list of str
        Group labels along x (methods).
    series : list of dict
        Keys ``label`` (legend: the dataset), ``mean`` and ``sd`` (one value
        per group, in percent; NaN where missing), ``n`` (runs per group).
    """
    fig = _figure(max(7.5, 1.1 * len(groups) + 4.5), 4.2)
    ax = fig.add_subplot()
    x = np.arange(len(groups))
    width = 0.8 / max(1, len(series))
    matplotlib, _ = require_matplotlib()
    cmap = matplotlib.colormaps["Set2"]
    for i, s in enumerate(series):
        mean = np.asarray(s["mean"], dtype=float)
        sd = np.asarray(s["sd"], dtype=float)
        pos = x - 0.4 + width * (i + 0.5)
        bars = ax.bar(pos, mean, width, yerr=sd, capsize=3, label=s["label"], color=cmap(i % 8))
        for rect, value in zip(bars, mean, strict=True):
            if np.isfinite(value):
                ax.annotate(
                    f"{value:.1f}",
                    (rect.get_x() + rect.get_width() / 2, value),
                    xytext=(0, 2),
                    textcoords="offset points",
                    ha="center",
                    va="bottom",
                    fontsize=8,
                )
    ax.set_xticks(
        x,
        groups,
        rotation=20 if len(groups) > 4 else 0,
        ha="right" if len(groups) > 4 else "center",
    )
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 105)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(
        title="condition (mean ± sd over seeds)",
        fontsize=8,
        title_fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.01, 1),
    )
    return _png(fig)


def pr_curves(panels: list[dict], order: list[str]) -> bytes:
    """Precision-recall curves, one panel per condition.

    Parameters
    ----------
    panels : list of dict
        Keys ``title`` and ``curves``: a list of dicts with ``label``,
        ``key`` (method, for the colour), ``recall`` and ``precision`` (lists)
        and ``auc`` (percent).
    order : list of str
        Methods in legend/colour order.
    """
    rows, cols = _grid(len(panels))
    fig = _figure(5.2 * cols, 4.2 * rows)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, panel in zip(axes, panels, strict=False):
        for curve in panel["curves"]:
            ax.plot(
                curve["recall"],
                curve["precision"],
                label=f"{curve['label']} (AUC {curve['auc']:.1f}%)",
                color=_colour(curve["key"], order),
                lw=1.6,
            )
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_title(panel["title"], fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    return _png(fig)


def sensitivity(param: str, series: list[dict], order: list[str], percent_x: bool) -> bytes:
    """Training accuracy and AUC against one parameter (two panels).

    Parameters
    ----------
    param : str
        The parameter on the x axis.
    series : list of dict
        Keys ``label``, ``key`` (method), ``x`` (values), ``acc_mean``,
        ``acc_sd``, ``auc_mean``, ``auc_sd`` (percent; NaN where missing).
    percent_x : bool
        Show x as a percentage (for ratios in [0, 1]).
    """
    fig = _figure(11, 4.2)
    ax_acc, ax_auc = fig.subplots(1, 2)
    markers = "osD^v<>"
    for i, s in enumerate(series):
        x = np.asarray(s["x"], dtype=float) * (100 if percent_x else 1)
        style = {
            "color": _colour(s["key"], order),
            "marker": markers[i % len(markers)],
            "capsize": 3,
            "label": s["label"],
        }
        ax_acc.errorbar(x, s["acc_mean"], yerr=s["acc_sd"], **style)
        ax_auc.errorbar(x, s["auc_mean"], yerr=s["auc_sd"], **style)
    xlabel = f"{param} (%)" if percent_x else param
    for ax, ylabel in ((ax_acc, "training accuracy (%)"), (ax_auc, "AUC (%)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_ylim(0, 105)
        ax.grid(alpha=0.3)
    ax_acc.set_title(f"training accuracy vs {param}", fontsize=10)
    ax_auc.set_title(f"AUC vs {param}", fontsize=10)
    ax_auc.legend(fontsize=8, title="mean ± sd over seeds", title_fontsize=8)
    return _png(fig)


def training_curves(panels: list[dict], order: list[str]) -> bytes:
    """Training accuracy per epoch: mean line and a ±1 sd band per method.

    Parameters
    ----------
    panels : list of dict
        Keys ``title`` and ``series``: dicts with ``label``, ``key``,
        ``mean`` and ``sd`` (percent, one value per epoch) and ``n`` (seeds).
    """
    rows, cols = _grid(len(panels))
    fig = _figure(6.0 * cols, 4.2 * rows)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, panel in zip(axes, panels, strict=False):
        for s in panel["series"]:
            mean = np.asarray(s["mean"], dtype=float)
            sd = np.asarray(s["sd"], dtype=float)
            epochs = np.arange(1, mean.size + 1)
            colour = _colour(s["key"], order)
            ax.plot(epochs, mean, color=colour, lw=1.8, label=f"{s['label']} (n={s['n']} seeds)")
            ax.fill_between(epochs, mean - sd, mean + sd, color=colour, alpha=0.25, lw=0)
        ax.set_xlabel("epoch")
        ax.set_ylabel("training accuracy (%)")
        ax.set_ylim(0, 105)
        ax.set_title(panel["title"], fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, title="mean ± 1 sd", title_fontsize=8, loc="lower right")
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    return _png(fig)


def _area(layers: int) -> float:
    """Marker area in points^2 for a model with ``layers`` layers (proportional)."""
    return 22.0 * max(int(layers), 1)


def auc_vs_size(panels: list[dict], order: list[str]) -> bytes:
    """AUC against trained parameters (log x), marker area proportional to layers.

    The style of the paper's Fig. "AUC performance vs. Network Size".
    ``panels``: dicts with ``title`` and ``points``: dicts with ``label``,
    ``key``, ``params``, ``auc`` (percent), ``auc_sd`` and ``layers``.
    """
    rows, cols = _grid(len(panels))
    fig = _figure(6.6 * cols, 4.4 * rows)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    all_layers = sorted({p["layers"] for panel in panels for p in panel["points"]})
    for ax, panel in zip(axes, panels, strict=False):
        placed: list[tuple[float, float]] = []
        for p in sorted(panel["points"], key=lambda q: (q["params"], q["auc"])):
            colour = _colour(p["key"], order)
            ax.errorbar(p["params"], p["auc"], yerr=p["auc_sd"], color=colour, capsize=3, lw=1)
            ax.scatter(
                p["params"],
                p["auc"],
                s=_area(p["layers"]),
                color=colour,
                alpha=0.75,
                edgecolors="black",
                linewidths=0.6,
                zorder=3,
            )
            # Points of equal size and similar AUC would print their names on top of each
            # other: step the label down once per earlier neighbour.
            near = sum(
                1
                for x, y in placed
                if abs(math.log10(x) - math.log10(p["params"])) < 0.08 and abs(y - p["auc"]) < 6
            )
            placed.append((p["params"], p["auc"]))
            ax.annotate(
                p["label"],
                (p["params"], p["auc"]),
                xytext=(7, 5 - 11 * near),
                textcoords="offset points",
                fontsize=8,
            )
        ax.set_xscale("log")
        ax.set_xlabel("trained parameters (log scale)")
        ax.set_ylabel("AUC (%)")
        ax.set_ylim(0, 105)
        ax.set_title(panel["title"], fontsize=10)
        ax.grid(alpha=0.3, which="both")
        if panel["points"]:
            lo = min(p["params"] for p in panel["points"])
            hi = max(p["params"] for p in panel["points"])
            ax.set_xlim(max(lo / 3, 1), hi * 6)
        handles = [
            ax.scatter([], [], s=_area(n), color="0.7", edgecolors="black", linewidths=0.6)
            for n in all_layers
        ]
        ax.legend(
            handles,
            [f"{n} layers" for n in all_layers],
            title="marker area",
            fontsize=8,
            title_fontsize=8,
            loc="upper left",
            bbox_to_anchor=(1.01, 1),
            labelspacing=2.2,
            borderpad=1.2,
        )
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    return _png(fig)


def qualitative(rows: list[dict], methods: list[str], title: str) -> bytes:
    """Example queries with the reference frame each method retrieved.

    Parameters
    ----------
    rows : list of dict
        One per example query: ``query`` (image (H, W) in [0, 1]), ``query_label``,
        ``truth`` (image or None), ``truth_label``, and ``retrieved``: one dict
        per method with ``image``, ``label`` and ``correct`` (bool).
    methods : list of str
        Column headings after the query and the true reference.
    """
    n_cols = 2 + len(methods)
    fig = _figure(1.9 * n_cols, 1.25 * len(rows) + 0.6)
    axes = fig.subplots(len(rows), n_cols, squeeze=False)
    headings = ["query", "true place (reference)"] + list(methods)
    for r, row in enumerate(rows):
        cells = [(row["query"], row["query_label"], None), (row["truth"], row["truth_label"], None)]
        cells += [(m["image"], m["label"], m["correct"]) for m in row["retrieved"]]
        for c, (image, label, correct) in enumerate(cells):
            ax = axes[r, c]
            ax.set_xticks([])
            ax.set_yticks([])
            if image is not None:
                ax.imshow(image, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            if correct is not None:
                colour = "#1a9850" if correct else "#d73027"
                for spine in ax.spines.values():
                    spine.set_edgecolor(colour)
                    spine.set_linewidth(3.5)
                label = f"{label} {'correct' if correct else 'wrong'}"
                ax.set_xlabel(label, fontsize=7, color=colour)
            else:
                ax.set_xlabel(label, fontsize=7)
            if r == 0:
                ax.set_title(headings[c], fontsize=8)
    fig.suptitle(title, fontsize=10)
    return _png(fig)
