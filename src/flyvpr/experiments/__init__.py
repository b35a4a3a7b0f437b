"""The paper's experiments, driven by a config file; a report with tables and figures.

``flyvpr experiment CONFIG.toml --out DIR`` expands the config's grids
(datasets x methods x seeds x parameters) into runs and executes them,
resumably and in parallel (:func:`run_experiment`); ``flyvpr report DIR``
turns the run files into ``DIR/report.html`` and ``DIR/report.md``
(:func:`write_report`).  ``experiments/paper.toml`` in the repository
reproduces the paper's evaluation; the user guide's page on experiments
documents the config format.

The modules, in the order data flows through them:

* :mod:`~flyvpr.experiments.schema`: a declarative schema for TOML tables
  (dataclass fields that say what they accept) and its one checker;
* :mod:`~flyvpr.experiments.config`: the config's blocks declared with it,
  read into an :class:`ExperimentConfig`;
* :mod:`~flyvpr.experiments.runs`: a grid's runs, their identity, and how
  parameters reach a method's front end and filter;
* :mod:`~flyvpr.experiments.runner`: executes the runs and writes one file each;
* :mod:`~flyvpr.experiments.records`: reads those files back, checked;
* :mod:`~flyvpr.experiments.report`, :mod:`~flyvpr.experiments.sections`,
  :mod:`~flyvpr.experiments.document` and :mod:`~flyvpr.experiments.plots`:
  the report's content by grid kind, as blocks rendered by the Jinja2
  templates in ``templates/``, with matplotlib figures;
* :mod:`~flyvpr.experiments.reference`: the config reference of the user
  guide, generated from the schema.

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
