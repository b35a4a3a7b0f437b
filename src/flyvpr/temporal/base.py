"""Base classes of temporal filters over a score matrix.

A filter maps a score matrix S (n_query, n_reference; rows in query time
order; higher = more similar) to a filtered matrix of the same shape and never
modifies its input.  Online filters also process one row at a time with
``reset()`` and ``step(row)``.
"""

from __future__ import annotations

import numpy as np

from .._params import ParamsMixin
from .._validation import check_scores

__all__ = ["TemporalFilter", "OnlineFilter"]


class TemporalFilter(ParamsMixin):
    """Base of every temporal filter: validates, copies, and delegates to ``_filter``."""

    name = "filter"

    def fit(self, reference_scores=None):
        """Learn from the reference traverse's own scores, where the filter is trained.

        Parameters
        ----------
        reference_scores : array-like, shape (n_reference, n_reference), optional
            The front end's scores of the reference images against themselves.
            Untrained filters ignore it.  Query data must never be passed here.
        """
        if reference_scores is not None:
            check_scores(reference_scores, "reference_scores")
        return self

    def filter(self, S) -> np.ndarray:
        """Filter a whole traverse of scores.

        Parameters
        ----------
        S : array-like, shape (n_query, n_reference)

        Returns
        -------
        ndarray, same shape as S
        """
        arr = check_scores(S, "S")
        out = self._filter(
            np.array(arr, dtype=np.float32 if arr.dtype == np.float32 else np.float64)
        )
        if out.shape != arr.shape:  # a bug in a subclass, not a user error
            raise RuntimeError(
                f"{type(self).__name__} changed the shape {arr.shape} -> {out.shape}"
            )
        return out

    #: fitted attributes written to model files (see flyvpr.modelio)
    _state_names: tuple[str, ...] = ()

    def _get_state(self) -> dict:
        """Fitted attributes to save: arrays or scalars (online state is not saved)."""
        return {name: getattr(self, name) for name in self._state_names if hasattr(self, name)}

    #: saved scalar attributes and their checks (model files are validated against them)
    _state_scalars: dict = {}

    def _state_arrays(self, scalars: dict) -> dict | None:
        """Expected arrays of the saved state (see ``Encoder._state_arrays``).

        A filter that saves nothing declares an empty state; one that overrides
        :meth:`_get_state` without declaring its arrays returns None (generic checks only).
        """
        if not self._state_names and type(self)._get_state is TemporalFilter._get_state:
            return {}
        return None

    def _set_state(self, state: dict) -> None:
        """Restore what :meth:`_get_state` returned and start from a clean online state."""
        for name, value in state.items():
            setattr(self, name, value)
        if hasattr(self, "reset"):
            self.reset()

    def footprint(self, n_reference: int) -> dict:
        """Layers, parameters and neurons this filter adds on top of a front end."""
        return {"layers": 0, "params": 0, "neurons": 0}

    def _filter(self, S: np.ndarray) -> np.ndarray:
        raise NotImplementedError


class OnlineFilter(TemporalFilter):
    """A causal filter that can run one query frame at a time."""

    def reset(self) -> None:
        """Forget all past frames."""
        raise NotImplementedError

    def step(self, scores_row) -> np.ndarray:
        """Feed one query frame's scores (n_reference,) and return the filtered row."""
        row = check_scores(scores_row, "scores_row", ndim=1)
        return self._step(row)

    def _step(self, row: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _filter(self, S: np.ndarray) -> np.ndarray:
        self.reset()
        out = np.empty_like(S)
        for t in range(S.shape[0]):
            out[t] = self._step(S[t])
        return out
