"""A map build's per-frame work spread over local processes or a Dask cluster, in fixed chunks.

Encoding the frames of a recording is embarrassingly parallel once the front end has learned
what it learns from the whole traverse (kenyon's static-pixel mask and feature mean).  A
:class:`ChunkRunner` applies a function of a block of rows to consecutive chunks of
:data:`CHUNK` rows and concatenates the results in order.  The chunk boundaries depend on the
number of rows only, never on the number of workers, and the functions it is given compute each
row on its own, so the result is the same bytes with one process, ``n_jobs`` processes or a
cluster (``tests/test_map_parallel.py`` checks the map files).
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

import numpy as np

__all__ = ["CHUNK", "ChunkRunner", "check_parallel", "in_process"]

logger = logging.getLogger(__name__)

#: rows (frames) per task: large enough that shipping the fitted encoder to a worker is small
#: against the work, small enough to keep 2-16 workers busy on a few thousand frames
CHUNK = 256


def in_process(func, rows, what: str = ""):
    """``func(rows)``: the one-process stand-in for a :class:`ChunkRunner`."""
    return func(rows)


def check_parallel(n_jobs, scheduler) -> None:
    """Check ``n_jobs`` and ``scheduler`` of a map build.

    Raises
    ------
    TypeError
        If ``n_jobs`` is not an int or ``scheduler`` neither an address nor a Client.
    ValueError
        If ``n_jobs`` is 0 or below -1, or both are given.
    """
    if n_jobs is not None:
        if isinstance(n_jobs, bool) or not isinstance(n_jobs, (int, np.integer)):
            raise TypeError(
                f"jobs (n_jobs) must be an int >= 1 or -1 (all cores); got {type(n_jobs).__name__}"
            )
        if n_jobs == 0 or n_jobs < -1:
            raise ValueError(f"jobs (n_jobs) must be an int >= 1 or -1 (all cores); got {n_jobs}")
    if scheduler is not None:
        if n_jobs is not None:
            raise ValueError(
                "jobs (n_jobs) and scheduler: give one of them (a cluster's workers set its jobs)"
            )
        if not isinstance(scheduler, str) and not hasattr(scheduler, "submit"):
            raise TypeError(
                "scheduler must be a Dask scheduler address (tcp://host:8786) or a "
                f"dask.distributed.Client; got {type(scheduler).__name__}"
            )
        if isinstance(scheduler, str) and not scheduler.strip():
            raise ValueError("scheduler must be a Dask scheduler address; got an empty string")


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(
            "scheduler: building a map on a Dask cluster needs dask.distributed: "
            "pip install 'flyvpr[dask]'"
        ) from exc
    return distributed


class ChunkRunner:
    """Run a function over fixed chunks of rows on local processes or a Dask cluster.

    Use it as a context manager: entering connects to the scheduler (so an unreachable one
    fails before any frame is read), leaving closes the connection it opened.

    Parameters
    ----------
    n_jobs : int, optional
        Local worker processes (joblib's loky backend); -1 for all cores.  1 runs the chunks
        one after another in this process.
    scheduler : str or dask.distributed.Client, optional
        A Dask scheduler address (``tcp://host:8786``) or a connected Client.
    progress : bool
        Show a progress bar (on stderr) of the rows done, one per call.

    Raises
    ------
    ConnectionError
        On entering, if the scheduler cannot be reached.
    ImportError
        If ``scheduler`` is given and dask.distributed is not installed (the ``dask`` extra).
    """

    def __init__(self, n_jobs=None, scheduler=None, *, progress: bool = False):
        check_parallel(n_jobs, scheduler)
        if scheduler is not None:
            _import_distributed()
        self.n_jobs = n_jobs
        self.scheduler = scheduler
        self.progress = progress
        self._client: Any = None  # a dask.distributed Client while in the with block
        self._stack: contextlib.ExitStack[bool | None] | None = None

    @property
    def parallel(self) -> bool:
        """Whether anything was asked for besides the plain one-process build."""
        return self.n_jobs is not None or self.scheduler is not None

    def __enter__(self) -> ChunkRunner:
        self._stack = contextlib.ExitStack()
        if isinstance(self.scheduler, str):
            distributed = _import_distributed()
            try:
                client = distributed.Client(self.scheduler, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise ConnectionError(
                    f"scheduler: cannot reach the Dask scheduler at {self.scheduler!r} ({exc})"
                ) from None
            self._client = self._stack.enter_context(client)
        elif self.scheduler is not None:
            self._client = self.scheduler
        return self

    def __exit__(self, *exc) -> None:
        assert self._stack is not None  # set by __enter__
        self._stack.close()
        self._client = None

    def describe(self) -> str:
        if self._client is not None:
            return f"Dask scheduler {self._client.scheduler.address}"
        return f"{self.n_jobs} local process(es)" if self.n_jobs != 1 else "1 process"

    def __call__(self, func, rows, what: str = "encoding"):
        """``func`` applied to consecutive chunks of ``rows``, the results concatenated.

        Parameters
        ----------
        func : callable
            Takes an array of k rows and returns an array of k rows; picklable (it travels to
            the workers with what it is bound to).
        rows : ndarray, shape (n, ...)
        what : str
            The progress bar's label.

        Returns
        -------
        ndarray, shape (n, ...)
        """
        from joblib import Parallel, delayed, parallel_config

        n = len(rows)
        starts = range(0, n, CHUNK)
        tasks = (delayed(func)(rows[s : s + CHUNK]) for s in starts)
        if self._client is not None:
            config = parallel_config(backend="dask", client=self._client)
            n_jobs = -1
        elif self.n_jobs == 1:
            config = contextlib.nullcontext()
            n_jobs = 1
        else:
            config = parallel_config(backend="loky")
            n_jobs = self.n_jobs
        bar: Any = contextlib.nullcontext()  # or a tqdm bar (untyped)
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=n, desc=what, unit="frame")
        parts = []
        with config, bar:
            for part in Parallel(n_jobs=n_jobs, return_as="generator")(tasks):
                parts.append(part)
                if self.progress:
                    bar.update(len(part))
        return np.concatenate(parts)
