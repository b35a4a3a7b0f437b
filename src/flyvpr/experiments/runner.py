"""Run an experiment config: every run of every grid, resumable and in parallel.

Layout of the results folder ``DIR``::

    DIR/experiment.json      the config (text and parsed), sessions, machine
    DIR/config.toml          a copy of the config file
    DIR/runs/<run-id>.json   one file per run, written atomically

A run file holds ``status`` (``"ok"`` or ``"error"``), the run's ``spec``,
the benchmark ``protocol`` (data, frame range, roles, tolerance, the number
of queries with a true match), the
``machine`` it ran on and, when it succeeded, its ``result``; evaluation runs
also store ``predictions`` (best reference per query), ``confidence`` (that
score) and ``correct`` (1 where the prediction is within tolerance).

Every run file also holds ``data_fingerprint``, the fingerprint of its dataset
(:meth:`flyvpr.datasets.Benchmark.fingerprint`: the image files' paths, sizes
and modification times, and the ground truth), taken once per dataset and
invocation.

Resuming: runs whose file exists with status ``"ok"`` and the fingerprint of the
data as they are now are skipped, so an interrupted experiment continues where
it stopped.  A finished run whose data changed since, or whose file records no
fingerprint (written by an older flyvpr), runs again, with one warning per
dataset saying why.  A run file that is not JSON at all (cut short) counts as
not done: a warning names it and the run runs again; a parsed file of the wrong
shape stops the experiment.  A run that raises is recorded with status
``"error"`` and the exception, the other runs go on, the report lists the
failure, and the next invocation tries that run again.

Parallelism: runs are spread over processes with :class:`joblib.Parallel`
(backend ``loky`` by default).  ``backend="dask"`` sends them to a Dask
cluster (the scheduler in ``DASK_SCHEDULER_ADDRESS``/dask's
``scheduler-address`` config, else the current client, else a local cluster)
and ``backend="ray"`` to Ray (``RAY_ADDRESS``); the dataset paths must then be
readable on the workers.  Results come back to this process, which writes
the run files.  Timing runs execute afterwards, one at a time in this process,
so no other run competes for the CPU while they are measured.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import platform
import signal
import sys
import threading
import time
import traceback
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .._io import write_json_atomic, write_text_atomic
from .config import ExperimentConfig, load_config
from .records import MalformedJSONError, read_experiment, read_run
from .runs import RunSpec, load_benchmark_of

__all__ = ["run_experiment", "execute_run", "machine_info", "BACKENDS"]

logger = logging.getLogger(__name__)

#: joblib backends accepted by :func:`run_experiment`
BACKENDS = ("loky", "threading", "multiprocessing", "sequential", "dask", "ray")

#: frames used by the untimed warm-up of timing runs
_WARMUP_FRAMES = 100


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def machine_info() -> dict:
    """CPU model, cores and library versions of this machine (for the report's protocol)."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    usable: int | None
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count()
    from .._version import __version__

    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "flyvpr": __version__,
    }
    # torch is reported only when a run loaded it: importing it here would cost seconds.
    if "torch" in sys.modules:
        info["torch"] = sys.modules["torch"].__version__
    return info


def _json_safe(obj):
    """Plain JSON types; non-finite floats become None (the files use strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        value = float(obj)
        return value if math.isfinite(value) else None
    if obj is None or isinstance(obj, str):
        return obj
    return repr(obj)


# -- one run -------------------------------------------------------------------------------------
def execute_run(run: RunSpec) -> dict:
    """Perform one run and return its record (never raises for a failing run).

    Parameters
    ----------
    run : RunSpec
        From :meth:`ExperimentConfig.runs`.

    Returns
    -------
    dict
        The run file's content: ``status`` ``"ok"`` with ``result``, or
        ``"error"`` with ``error`` (type and message) and ``traceback``.
    """
    started = _now()
    t0 = time.perf_counter()
    record: dict = {"run_id": run.run_id, "spec": run.spec, "started": started}
    try:
        bench = load_benchmark_of(run)
        record["protocol"] = {
            **bench.protocol(),
            "n_query_with_match": int(np.count_nonzero(bench.ground_truth.any(axis=1))),
            "image_size": run.spec["image_size"],
            "speed": run.spec["speed"],
        }
        task = run.task
        if task == "train":
            record.update(_train(run, bench))
        elif task in ("evaluate", "timing"):
            record.update(_evaluate(run, bench, timing=task == "timing"))
        else:
            raise ValueError(f"unknown task {task!r}")
        record["status"] = "ok"
    except Exception as exc:  # recorded, reported, retried on the next invocation
        logger.warning("run %s failed: %s: %s", run.run_id, type(exc).__name__, exc)
        record["status"] = "error"
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc()
    record["elapsed_s"] = time.perf_counter() - t0
    record["machine"] = machine_info()
    return _json_safe(record)


def _evaluate(run: RunSpec, bench, timing: bool) -> dict:
    from .. import metrics
    from ..evaluation import evaluate_method

    spec = run.spec
    size = tuple(spec["image_size"])
    cache = False if timing else run.cache
    t0 = time.perf_counter()
    ref = bench.reference.load_images(size, cache=cache, progress=False)
    t1 = time.perf_counter()
    qry = bench.query.load_images(size, cache=cache, progress=False)
    t2 = time.perf_counter()
    gt = bench.ground_truth
    kwargs = {
        "seed": spec["seed"],
        "frontend_params": spec["frontend_params"],
        "filter_params": spec["filter_params"],
    }
    if timing and run.warmup:
        # First calls pay JIT compilation and lazy imports; the paper times steady state.
        n = min(_WARMUP_FRAMES, len(ref), len(qry))
        evaluate_method(spec["method"], ref[:n], qry[:n], gt[:n, :n], **kwargs)
    result, S = evaluate_method(
        spec["method"],
        ref,
        qry,
        gt,
        load_s=t2 - t0,
        return_scores=True,
        measure_model_bytes=True,
        **kwargs,
    )
    result["timing"].update(load_reference_s=t1 - t0, load_query_s=t2 - t1, cached=bool(cache))
    best, confidence = metrics.best_match(S)
    correct = gt[np.arange(len(best)), best]
    return {
        "result": result,
        "predictions": best.tolist(),
        "confidence": [float(c) for c in confidence],  # exact: the curve can be recomputed
        "correct": correct.astype(int).tolist(),
    }


def _train(run: RunSpec, bench) -> dict:
    from ..methods import make_method

    spec = run.spec
    ref = bench.reference.load_images(tuple(spec["image_size"]), cache=run.cache, progress=False)
    model = make_method(
        spec["method"], spec["seed"], spec["frontend_params"], spec["filter_params"]
    )
    front = model.frontend
    t0 = time.perf_counter()
    front.fit(ref)
    fit_s = time.perf_counter() - t0
    history = getattr(front, "accuracy_history_", None)
    if history is None:
        raise ValueError(
            f"method {spec['method']!r}: its front end {type(front).__name__} records no "
            "per-epoch training accuracy (attribute accuracy_history_), which a "
            "training_curve grid needs"
        )
    loss = getattr(front, "loss_history_", None)
    return {
        "result": {
            "method": spec["method"],
            "seed": spec["seed"],
            "n_reference": len(ref),
            "train_accuracy": getattr(front, "train_accuracy_", None),
            "accuracy_history": np.asarray(history, dtype=float).tolist(),
            "loss_history": None if loss is None else np.asarray(loss, dtype=float).tolist(),
            "fit_s": fit_s,
            "footprint": front.footprint(),
        }
    }


# -- the experiment ------------------------------------------------------------------------------
def _finished(path: Path) -> dict | None:
    """The record of a finished run from its file; None if there is none.

    A file that is not JSON at all (cut short by a full disk or a copy that stopped) holds
    no run, so that run is not done: one warning, and it runs again.  A parsed file of
    another shape (a missing key, another run's id) is refused, as it may hold results.
    """
    if not path.exists():
        return None
    try:
        record = read_run(path)
    except MalformedJSONError as exc:
        logger.warning("%s; running it again", exc)
        return None
    return record if record["status"] == "ok" else None


def _data_change(old: dict, new: dict) -> str | None:
    """What differs between a run's recorded data fingerprint and the data's now, in words;
    None when they are the same."""
    if old == new:
        return None
    changes = []
    for role in ("reference", "query"):
        was, now = old.get(role) or {}, new[role]
        if was.get("n_images") != now["n_images"]:
            changes.append(f"{role}: {now['n_images']} images, were {was.get('n_images', '?')}")
        elif was.get("files") != now["files"]:
            changes.append(f"{role}: other image files, sizes or modification times")
    was, now = old.get("ground_truth") or {}, new["ground_truth"]
    if not changes and was != now:
        changes.append(f"ground truth: {now['n_true']} true matches, were {was.get('n_true', '?')}")
    return "; ".join(changes) or "another fingerprint"


def _pending(runs: list[RunSpec], runs_dir: Path, fingerprints: dict[str, dict]) -> list:
    """The runs to do: those without a finished run file, and those whose file was written
    for other data than the dataset's now, or records no fingerprint of its data (a file of
    an older flyvpr: the data cannot be shown to be the same), with one warning per dataset
    and reason."""
    pending = []
    changed: dict[tuple[str, str], int] = {}
    unknown: dict[str, int] = {}
    for run in runs:
        record = _finished(runs_dir / f"{run.run_id}.json")
        if record is None:
            pending.append(run)
            continue
        name = run.spec["dataset"]["name"]
        old = record.get("data_fingerprint")
        if not isinstance(old, dict):
            unknown[name] = unknown.get(name, 0) + 1
            pending.append(run)
            continue
        why = _data_change(old, fingerprints[name])
        if why is not None:
            changed[name, why] = changed.get((name, why), 0) + 1
            pending.append(run)
    for (name, why), n in changed.items():
        logger.warning(
            "dataset %r: data changed since the run: %s; running %s again",
            name, why, _finished_runs(n),
        )  # fmt: skip
    for name, n in unknown.items():
        logger.warning(
            "dataset %r: the files of %s, written by an older flyvpr, record no fingerprint "
            "of their data, which may have changed since; running them again",
            name, _finished_runs(n),
        )  # fmt: skip
    return pending


def _finished_runs(n: int) -> str:
    return "1 finished run" if n == 1 else f"{n} finished runs"


class Terminated(SystemExit):
    """Raised in the main thread on SIGTERM while an experiment runs (exit status 143)."""


@contextlib.contextmanager
def _exit_on_sigterm():
    """Turn SIGTERM into :class:`Terminated` while the block runs, so it unwinds like Ctrl-C.

    Unwinding runs the clean-ups a plain SIGTERM would skip: joblib terminates
    its worker processes and an atomic write in progress removes its temporary
    file.  Installed only from the main thread and only over the default
    handler, so an application's own SIGTERM handler is left alone.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def handler(signum, frame):
        raise Terminated(128 + signal.SIGTERM)

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    except Terminated:
        logger.warning("terminated (SIGTERM); finished runs are kept, the rest run next time")
        raise
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _check_jobs(n_jobs) -> int:
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, (int, np.integer)):
        raise TypeError(f"n_jobs must be an int (-1: all cores); got {type(n_jobs).__name__}")
    if n_jobs == 0:
        raise ValueError("n_jobs must be a non-zero int (-1: all cores); got 0")
    return int(n_jobs)


@contextlib.contextmanager
def _backend_context(backend: str):
    """joblib's parallel_config for ``backend``, connecting to Dask or Ray when asked."""
    from joblib import parallel_config

    if backend == "dask":
        try:
            import dask
            import distributed
        except ImportError as exc:
            raise ImportError(
                "backend 'dask' needs dask.distributed: pip install 'dask[distributed]'"
            ) from exc
        with contextlib.ExitStack() as stack:
            address = dask.config.get("scheduler-address", None)
            if address:
                client = stack.enter_context(distributed.Client(address))
            else:
                try:
                    client = distributed.get_client()
                except ValueError:  # no client yet: a local cluster for this experiment
                    logger.info("no Dask scheduler configured; starting a local cluster")
                    client = stack.enter_context(distributed.Client())
            with parallel_config(backend="dask", client=client):
                yield
    elif backend == "ray":
        try:
            from ray.util.joblib import register_ray
        except ImportError as exc:
            raise ImportError("backend 'ray' needs ray: pip install 'ray'") from exc
        register_ray()
        with parallel_config(backend="ray"):
            yield
    elif backend in ("loky", "multiprocessing"):
        with parallel_config(backend=backend, initializer=_ignore_interrupts):
            yield
    else:
        with parallel_config(backend=backend):
            yield


def _ignore_interrupts() -> None:
    """Start of a local worker process: ignore SIGINT.

    Ctrl-C (or ``timeout -s INT``) signals the whole process group, workers included; each
    worker would print a KeyboardInterrupt traceback from wherever it was.  The calling
    process handles the interrupt and terminates its workers, so they need not.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: loky restarts a worker whose memory grew by more than 300 MB since it started (its "memory
#: leak" check): a worker that has loaded a few data sets and compiled the numba kernels
#: does, and loky then warns of a stopped worker.  The runs go on in a fresh worker; nothing
#: is lost, so the warning is left out.
_LOKY_RESTART = "A worker stopped while some jobs were given to the executor"


@contextlib.contextmanager
def _quiet_loky_restarts():
    """Leave out loky's warning of a restarted worker (only that warning, only from loky)
    while the runs go on.  The filter is the process's (loky warns from its own thread)."""
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message=_LOKY_RESTART, category=UserWarning, module=r"joblib\.externals\.loky"
        )
        yield


def _run_parallel(runs: list[RunSpec], n_jobs: int, backend: str):
    """Yield run records as they finish."""
    from joblib import Parallel, delayed, effective_n_jobs

    if not runs:
        return
    with _backend_context(backend):
        tasks = (delayed(execute_run)(run) for run in runs)
        try:
            parallel = Parallel(n_jobs=n_jobs, return_as="generator_unordered")
        except ValueError:
            # Backends without result generators (multiprocessing, ray): small batches,
            # so finished runs are still written while the rest go on.
            parallel = Parallel(n_jobs=n_jobs)
            batch = max(1, 2 * effective_n_jobs(n_jobs))
            runs = list(runs)
            for start in range(0, len(runs), batch):
                yield from parallel(delayed(execute_run)(r) for r in runs[start : start + batch])
            return
        yield from parallel(tasks)


def _where(config: ExperimentConfig, name: str) -> str:
    """The config's file and the ``[[datasets]]`` block of dataset ``name``, for messages."""
    number = list(config.datasets).index(name) + 1
    return f"{config.path or 'config'} [[datasets]] #{number} ({name!r})"


def _load_datasets(config: ExperimentConfig, runs: list[RunSpec]) -> dict:
    """Load every dataset the runs read, once, with its fingerprint: missing data fails
    before any run starts (and before anything is written), with the config's file and
    ``[[datasets]]`` block named.  Returns name -> (benchmark, fingerprint)."""
    from ..datasets import load_benchmark

    loaded: dict = {}
    for run in runs:
        name = run.spec["dataset"]["name"]
        if name in loaded:
            continue
        try:
            bench = load_benchmark(run.spec["dataset"]["loader"], **run.dataset_options)
            loaded[name] = (bench, bench.fingerprint())
        except (OSError, ValueError) as exc:
            raise _named(exc, _where(config, name)) from exc
    return loaded


def _prepare(config: ExperimentConfig, runs: list[RunSpec], datasets: dict, progress: bool):
    """Check and decode, before the work, what the runs will read: a run that evaluates
    needs a query with a true match (every metric is undefined without one), and the image
    cache is filled here before parallel workers would each decode the same files."""
    from ..evaluation import check_true_matches

    checked: set = set()
    decoded: set = set()
    for run in runs:
        spec = run.spec
        name = spec["dataset"]["name"]
        queries = (name, json.dumps(spec["speed"]), spec["seed"] if spec["speed"] else None)
        images = (*queries, tuple(spec["image_size"]))
        check = run.task != "train" and queries not in checked
        decode = run.task != "timing" and run.cache is not False and images not in decoded
        if not (check or decode):
            continue
        where = _where(config, name)
        if spec["speed"] is not None:
            where += f" at speed {spec['speed']} (seed {spec['seed']})"
        try:
            bench = load_benchmark_of(run, datasets[name][0])
            if check:
                check_true_matches(bench)
                checked.add(queries)
            if decode:
                bench.load_images(tuple(spec["image_size"]), cache=run.cache, progress=progress)
                decoded.add(images)
        except (OSError, ValueError) as exc:
            raise _named(exc, where) from exc


def _named(exc: Exception, where: str) -> Exception:
    """``exc`` again (its type where it takes a message) with ``where`` before its message."""
    message = f"{where}: {exc}"
    try:
        return type(exc)(message)
    except Exception:  # a type that wants other arguments
        return ValueError(message)


def _check_queries(config: ExperimentConfig, n_query: dict[str, int]) -> None:
    """A qualitative grid's ``queries`` must be query positions of each of its datasets."""
    for grid in config.grids:
        if grid.kind != "qualitative" or grid.queries is None:
            continue
        for name in grid.datasets:
            n = n_query[name]
            beyond = [q for q in grid.queries if q >= n]
            if beyond:
                raise ValueError(
                    f"{config.path or 'config'} [[grids]] {grid.name!r}: queries "
                    f"{', '.join(map(str, beyond))} lie beyond the {n} queries of dataset "
                    f"{name!r} (positions 0-{n - 1})"
                )


def _want_progress(progress) -> bool:
    if progress is None:
        return sys.stderr.isatty()
    return bool(progress)


def run_experiment(config_path, out_dir, n_jobs: int = 1, backend: str = "loky", progress=None):
    """Run every grid of an experiment config, skipping runs already finished.

    Parameters
    ----------
    config_path : str or Path
        TOML experiment file (schema: :mod:`flyvpr.experiments.config`).
    out_dir : str or Path
        Results folder; created if needed.  Run files go to ``out_dir/runs``.
    n_jobs : int
        Worker processes (joblib convention: -1 = all cores).
    backend : str
        A joblib backend: ``'loky'`` (default), ``'dask'`` or ``'ray'``
        (optional installs), or ``'threading'``/``'multiprocessing'``/``'sequential'``.
    progress : bool, optional
        Show a progress bar; ``None``: only when stderr is a terminal.

    Returns
    -------
    dict
        ``n_runs`` (distinct runs in the config), ``n_skipped`` (already
        finished), ``ran`` (ids run now), ``errors`` (id -> message of runs
        that failed now), ``elapsed_s`` and ``out_dir``.

    Raises
    ------
    FileNotFoundError
        If the config or a dataset is missing (checked before any run).
    ValueError, TypeError
        For an invalid config, ``n_jobs`` or ``backend``.
    ImportError
        For the dask/ray backends when they are not installed.
    """
    n_jobs = _check_jobs(n_jobs)
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    with _exit_on_sigterm():
        return _run(config_path, out_dir, n_jobs, backend, progress)


def _run(config_path, out_dir, n_jobs: int, backend: str, progress) -> dict:
    from tqdm.auto import tqdm

    config = load_config(config_path)
    out_dir = Path(out_dir)
    runs_dir = out_dir / "runs"
    t_start = time.perf_counter()
    started = _now()

    runs = config.runs()
    plan = config.plan()
    # the data first: a dataset that fails to load leaves the results folder as it was
    datasets = _load_datasets(config, runs)
    fingerprints = {name: fingerprint for name, (_, fingerprint) in datasets.items()}
    _check_queries(config, {name: bench.n_query for name, (bench, _) in datasets.items()})
    pending = _pending(runs, runs_dir, fingerprints)
    n_skipped = len(runs) - len(pending)
    logger.info("%d runs, %d already finished, %d to run", len(runs), n_skipped, len(pending))

    show = _want_progress(progress)
    _prepare(config, pending, datasets, show)
    del datasets  # (each run loads its own; the ground truths need not stay in this process)
    runs_dir.mkdir(parents=True, exist_ok=True)
    experiment_file = out_dir / "experiment.json"
    sessions = read_experiment(experiment_file)["sessions"] if experiment_file.exists() else []
    session = {
        "started": started,
        "n_jobs": n_jobs,
        "backend": backend,
        "n_runs": len(runs),
        "n_skipped": n_skipped,
        "machine": machine_info(),
    }
    write_text_atomic(out_dir / "config.toml", config.text)
    experiment_record = {
        "config_path": str(Path(config_path).resolve()),
        "config_text": config.text,
        "config": config.to_dict(),
        "plan": plan,
        "sessions": sessions + [session],  # ``session`` is updated in place when done
    }
    write_json_atomic(experiment_file, _json_safe(experiment_record))

    ran: list[str] = []
    errors: dict[str, str] = {}
    parallel_runs = [r for r in pending if r.task != "timing"]
    timing_runs = [r for r in pending if r.task == "timing"]
    with tqdm(total=len(pending), desc="runs", unit="run", disable=not show) as bar:

        def store(record: dict) -> None:
            # the data as they were when this invocation began: data changed while the
            # runs went on then differ from it next time, and those runs run again
            record["data_fingerprint"] = fingerprints[record["spec"]["dataset"]["name"]]
            write_json_atomic(runs_dir / f"{record['run_id']}.json", record)
            ran.append(record["run_id"])
            if record["status"] != "ok":
                errors[record["run_id"]] = record["error"]
            bar.set_postfix_str(f"{len(errors)} failed" if errors else "", refresh=False)
            bar.update(1)

        # Closing the generator on any exit (an error, Ctrl-C, SIGTERM) makes joblib
        # terminate its worker processes instead of leaving them to finish their runs.
        with (
            _quiet_loky_restarts(),
            contextlib.closing(_run_parallel(parallel_runs, n_jobs, backend)) as records,
        ):
            for record in records:
                store(record)
        for run in timing_runs:
            store(execute_run(run))

    session.update(finished=_now(), n_ran=len(ran), n_errors=len(errors))
    write_json_atomic(experiment_file, _json_safe(experiment_record))
    return {
        "n_runs": len(runs),
        "n_skipped": n_skipped,
        "ran": ran,
        "errors": errors,
        "elapsed_s": time.perf_counter() - t_start,
        "out_dir": str(out_dir),
    }
