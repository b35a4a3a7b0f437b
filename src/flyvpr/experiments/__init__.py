"""The paper's experiments, driven by a config file; a report with tables and figures.

``flyvpr experiment CONFIG.toml --out DIR`` expands the config's grids
(datasets x methods x seeds x parameters) into runs and executes them,
resumably and in parallel (:func:`run_experiment`); ``flyvpr report DIR``
turns the run files into ``DIR/report.html`` and ``DIR/report.md``
(:func:`write_report`).  The config schema is documented in
:mod:`flyvpr.experiments.config`; ``experiments/paper.toml`` in the repository
reproduces the paper's evaluation.

Importing this package loads neither matplotlib nor torch: figures are drawn
by :mod:`flyvpr.experiments.plots` only when a report is written.
"""

from .config import KINDS, ExperimentConfig, load_config, parse_config
from .report import write_report
from .runner import BACKENDS, execute_run, run_experiment

__all__ = [
    "KINDS",
    "BACKENDS",
    "ExperimentConfig",
    "load_config",
    "parse_config",
    "run_experiment",
    "execute_run",
    "write_report",
]
