"""Runs: what one grid point computes, its identity, and how parameters reach a method.

A run is (task, dataset block, method, seed, every front-end and filter
constructor argument with defaults filled in, speed, image size).  Its id is a
readable slug plus a hash of that spec, so the same run requested by two
grids is computed once (spelling out a default value changes nothing, nor does
writing a whole number as ``1`` or ``1.0``), and an edited grid only adds the
runs that are new.  Dataset options enter as written in the file, so moving
the checkout keeps the ids.  The data themselves are not part of the identity:
each run file records their fingerprint
(:meth:`flyvpr.datasets.Benchmark.fingerprint`), and a resumed experiment runs
again a run whose data changed since.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import re
from dataclasses import dataclass

__all__ = [
    "RunSpec",
    "run_id_of",
    "route_params",
    "full_params",
    "expand_grid",
    "load_benchmark_of",
]


@dataclass(frozen=True)
class RunSpec:
    """One run: what is hashed into its id, and what the worker needs besides.

    Attributes
    ----------
    run_id : str
        ``<task>-<dataset>-<method>-s<seed>-<hash12>``, safe as a file name.
    spec : dict
        The run's identity (JSON-serialisable): ``task``, ``dataset`` (name,
        loader, options as written), ``method``, ``seed``, ``frontend_params``,
        ``filter_params``, ``speed``, ``image_size``.
    dataset_options : dict
        Loader options with resolved paths.
    cache : bool or str
        Image cache setting (not part of the identity).
    warmup : bool
        Timing runs only: do an untimed warm-up run first.
    """

    run_id: str
    spec: dict
    dataset_options: dict
    cache: bool | str = True
    warmup: bool = True

    @property
    def task(self) -> str:
        """``'evaluate'``, ``'train'`` or ``'timing'``."""
        return self.spec["task"]


def load_benchmark_of(run: RunSpec, dataset=None):
    """The benchmark a run reads: its dataset, its queries thinned to its speed profile.

    Parameters
    ----------
    run : RunSpec
    dataset : flyvpr.datasets.Benchmark, optional
        The run's dataset, already loaded (every query frame); ``None`` loads it.

    Returns
    -------
    flyvpr.datasets.Benchmark

    Raises
    ------
    FileNotFoundError, ValueError
        From the loader, for missing or malformed data.
    """
    from ..datasets import load_benchmark
    from ..evaluation import speed_profile

    spec = run.spec
    bench = dataset
    if bench is None:
        bench = load_benchmark(spec["dataset"]["loader"], **run.dataset_options)
    if spec["speed"] is not None:
        keep = speed_profile(bench.n_query, spec["speed"], random_state=spec["seed"])
        bench = bench.subset_queries(keep)
    return bench


def run_id_of(spec: dict) -> str:
    """Stable id of a run spec: a readable slug and 12 hex digits of its SHA-256.

    Parameters
    ----------
    spec : dict
        The ``spec`` of a :class:`RunSpec`.

    Returns
    -------
    str
        ``<task>-<dataset>-<method>-s<seed>-<hash12>``.

    Notes
    -----
    The hash is taken of a canonical form of the spec in which a float that is a whole
    number is written as an int, so ``1`` and ``1.0`` give one id; the spec itself, which
    the method receives, keeps the values as given.
    """
    canonical = json.dumps(_canonical(spec), sort_keys=True, separators=(",", ":"), allow_nan=False)
    digest = hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:12]
    slug = f"{spec['task']}-{spec['dataset']['name']}-{spec['method']}-s{spec['seed']}"
    slug = re.sub(r"[^A-Za-z0-9._+-]", "_", slug)
    return f"{slug}-{digest}"


def _canonical(value):
    """``value`` with every float that is a whole number written as an int (``1.0`` -> ``1``).

    So ``speed_prior = 1`` names the same run as its default ``1.0``.  Booleans stay
    booleans (``True`` is not ``1``), other floats stay floats, and nothing else changes.
    """
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, dict):
        return {key: _canonical(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(item) for item in value]
    return value


def _defaults(cls) -> dict:
    """Constructor defaults of ``cls`` except ``random_state``, as JSON values."""
    out = {}
    for p in inspect.signature(cls.__init__).parameters.values():
        if p.name in ("self", "random_state") or p.default is inspect.Parameter.empty:
            continue
        if p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
            continue
        try:
            out[p.name] = json.loads(json.dumps(p.default, allow_nan=False))
        except (TypeError, ValueError):
            out[p.name] = repr(p.default)
    return out


def full_params(spec, front: dict, filt: dict) -> tuple[dict, dict]:
    """Every constructor argument, defaults filled in.

    So a run's identity does not depend on whether a config spells out a
    default value.

    Parameters
    ----------
    spec : flyvpr.methods.MethodSpec
    front, filt : dict
        Front-end and filter arguments given by the config.

    Returns
    -------
    (dict, dict)
        The front end's and the filter's full arguments (no ``random_state``).
    """
    from ..frontends import FRONTENDS
    from ..methods import holds_repeats
    from ..temporal import FILTERS

    front_cls = FRONTENDS[spec.frontend]
    defaults = _defaults(FILTERS[spec.filter]) if spec.filter else {}
    if "hold_repeats" in defaults:  # as make_method sets it
        defaults["hold_repeats"] = holds_repeats(front_cls)
    return {**_defaults(front_cls), **front}, {**defaults, **filt}


def route_params(spec, params: dict, where: str = "") -> tuple[dict, dict]:
    """Split ``params`` into front-end and filter constructor arguments of a method.

    A key goes to the part whose constructor takes it; ``frontend.KEY`` and
    ``filter.KEY`` choose explicitly, and must for a name both parts take
    (``epochs`` of ``flynet+rnn``), which would otherwise set one part only.

    Parameters
    ----------
    spec : flyvpr.methods.MethodSpec
    params : dict
        Parameter name -> value.
    where : str
        Prefix of error messages (file and block).

    Returns
    -------
    (dict, dict)
        Front-end and filter arguments.

    Raises
    ------
    ValueError
        For ``random_state`` (it comes from the seeds), for a key neither
        constructor takes (the message lists what they take) and for an unprefixed
        key both take.
    """
    from ..frontends import FRONTENDS
    from ..temporal import FILTERS

    front_names = set(FRONTENDS[spec.frontend]._param_names())
    filt_names = set(FILTERS[spec.filter]._param_names()) if spec.filter else set()
    front: dict = {}
    filt: dict = {}
    for key, value in params.items():
        if key.startswith("frontend."):
            bare, names, target = key[len("frontend.") :], front_names, front
        elif key.startswith("filter."):
            bare, names, target = key[len("filter.") :], filt_names, filt
        elif key in front_names:
            bare, names, target = key, front_names, front
        else:
            bare, names, target = key, filt_names, filt
        if bare == "random_state":
            raise ValueError(f"{where}: set random_state through 'seeds', not params")
        if key in front_names and key in filt_names:
            raise ValueError(
                f"{where}: {key!r} is a parameter of both parts of method {spec.name!r} "
                f"(front end {spec.frontend!r} and filter {spec.filter!r}); write "
                f"'frontend.{key}' or 'filter.{key}' (or both)"
            )
        if bare not in names:
            takes = f"its front end {spec.frontend!r} takes {_names(front_names)}"
            if spec.filter:
                takes += f" and its filter {spec.filter!r} takes {_names(filt_names)}"
            raise ValueError(
                f"{where}: {key!r} is not a parameter of method {spec.name!r}; {takes}"
            )
        target[bare] = value
    return front, filt


def _names(params: set[str]) -> list[str]:
    return sorted(params - {"random_state"})


def expand_grid(grid, datasets: dict, image_size, cache) -> list[dict]:
    """The runs of one grid with their coordinates, in order datasets x methods x seeds x params.

    Parameters
    ----------
    grid : flyvpr.experiments.config.GridBlock
    datasets : dict of str to DatasetBlock
    image_size : (int, int)
    cache : bool or str

    Returns
    -------
    list of dict
        Keys ``run`` (:class:`RunSpec`), ``dataset``, ``method``, ``seed`` and
        ``combo`` (this run's value of every ``params`` key).
    """
    from ..methods import METHODS

    items = []
    points = [
        (datasets[name], method, seed, combo)
        for name in grid.datasets
        for method in grid.methods
        for seed in grid.seeds_for(method)
        for combo in grid.param_combinations()
    ]
    for ds, method, seed, combo in points:
        params = {**combo, **grid.method_params.get(method, {})}
        front, filt = full_params(METHODS[method], *route_params(METHODS[method], params))
        spec = {
            "task": grid.task,
            "dataset": {"name": ds.name, "loader": ds.loader, "options": ds.options},
            "method": method,
            "seed": seed,
            "frontend_params": front,
            "filter_params": filt,
            "speed": list(grid.speed) if isinstance(grid.speed, tuple) else grid.speed,
            "image_size": list(image_size),
        }
        run = RunSpec(run_id_of(spec), spec, dict(ds.resolved), cache=cache, warmup=grid.warmup)
        coords = {"dataset": ds.name, "method": method, "seed": seed, "combo": combo}
        items.append({"run": run, **coords})
    return items
