"""Methods: a single-frame front end, optionally followed by a temporal filter.

A method name is a front end's registry name (``flynet``), a front end and a
filter joined by ``+`` (``flynet+cann``), or an alias (``seqslam`` is SeqSLAM
on patch-normalised pixels, the paper's SeqSLAM baseline).  ``METHODS`` is
derived from :data:`flyvpr.frontends.FRONTENDS` and
:data:`flyvpr.temporal.FILTERS`, so every combination is available and the
CLI's choices never need a hand-written list.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ._validation import check_random_state
from .frontends import FRONTENDS, Encoder
from .temporal import FILTERS, TemporalFilter

__all__ = [
    "Method",
    "MethodSpec",
    "METHODS",
    "ALIASES",
    "DEFAULT_METHOD",
    "make_method",
    "method_names",
]

#: the method ``flyvpr map``, ``flyvpr localize``, ``flyvpr demo`` and
#: :class:`flyvpr.localization.Localizer` use unless told otherwise: the fly-inspired front end
#: (fixed optic lobe + Kenyon-cell expansion, 512 bytes per place) with the CANN, the best
#: measured fly-inspired hybrid (docs/results/accuracy.md)
DEFAULT_METHOD = "kenyon+cann"
#: short names for combinations the literature calls by one name
ALIASES = {"seqslam": "pixels+seqslam"}


@dataclass(frozen=True)
class MethodSpec:
    """What a method name stands for."""

    name: str
    frontend: str
    filter: str | None = None

    @property
    def description(self) -> str:
        front = FRONTENDS[self.frontend]
        text = (front.__doc__ or front.__name__).strip().splitlines()[0]
        if self.filter is not None:
            filt = FILTERS[self.filter]
            text += " + " + (filt.__doc__ or filt.__name__).strip().splitlines()[0]
        return text

    def _parts(self):
        yield FRONTENDS[self.frontend]
        if self.filter is not None:
            yield FILTERS[self.filter]

    @property
    def requires(self) -> tuple[str, ...]:
        """Importable modules the method needs beyond the core install."""
        return tuple(sorted({m for part in self._parts() for m in getattr(part, "requires", ())}))

    @property
    def extras(self) -> tuple[str, ...]:
        """pip extras (``pip install 'flyvpr[EXTRA]'``) that provide :attr:`requires`."""
        return tuple(
            sorted(
                {
                    getattr(part, "extra", "torch")
                    for part in self._parts()
                    if getattr(part, "requires", ())
                }
            )
        )


def _build_registry() -> dict[str, MethodSpec]:
    reg = {}
    for front in FRONTENDS:
        reg[front] = MethodSpec(front, front)
        for filt in FILTERS:
            reg[f"{front}+{filt}"] = MethodSpec(f"{front}+{filt}", front, filt)
    for alias, target in ALIASES.items():
        spec = reg[target]
        reg[alias] = MethodSpec(alias, spec.frontend, spec.filter)
    return reg


#: method name -> spec
METHODS: dict[str, MethodSpec] = _build_registry()


def method_names(available_only: bool = False) -> list[str]:
    """All method names; with ``available_only`` those whose extras are importable."""
    names = list(METHODS)
    if available_only:
        names = [n for n in names if _modules_available(METHODS[n].requires)]
    return names


def _modules_available(modules) -> bool:
    import importlib.util

    return all(importlib.util.find_spec(mod) is not None for mod in modules)


def make_method(name: str, random_state=None, frontend_params=None, filter_params=None) -> Method:
    """Build an unfitted :class:`Method` from its registry name.

    Parameters
    ----------
    name : str
        A key of :data:`METHODS`.
    random_state : None, int or Generator
        Passed to the parts that take one (unless their parameters set it), as one
        Generator they share (the front end draws first, in ``fit``).  An int seeds it
        afresh at every :meth:`Method.fit`, so a method refitted gives the same map; a
        Generator goes on with its stream.
    frontend_params, filter_params : dict, optional
        Constructor keyword arguments of the front end and of the filter.

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones) or unknown parameters.
    TypeError
        For a name that is not a str.
    """
    if not isinstance(name, str):
        raise TypeError(
            f"method must be a method name (a str, see `flyvpr methods`); got {type(name).__name__}"
        )
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; known methods: {', '.join(METHODS)}")
    spec = METHODS[name]
    rng = check_random_state(random_state)
    seeded = []
    frontend = _construct(FRONTENDS[spec.frontend], frontend_params or {}, rng)
    if frontend.get_params().get("random_state") is rng:
        seeded.append("frontend")
    filt = None
    if spec.filter is not None:
        filt = _construct(FILTERS[spec.filter], filter_params or {}, rng)
        if filt.get_params().get("random_state") is rng:
            seeded.append("filter")
        hold_default(frontend, filt, filter_params or {})
    elif filter_params:
        raise ValueError(
            f"method {name!r} has no temporal filter; got filter_params {filter_params}"
        )
    seed = (
        None
        if random_state is None or isinstance(random_state, np.random.Generator)
        else int(random_state)
    )
    return Method(name, frontend, filt, seed=seed, seeded=tuple(seeded))


def holds_repeats(frontend) -> bool:
    """Whether a filter behind ``frontend`` (an encoder or its class) holds repeated score rows
    by default: not where its scores repeat on frames that differ by sensor noise only
    (``repeats_on_noise``), for there a repeated row may be a robot standing where its map's
    robot also stood, and the map's place index runs on while the image stays."""
    return not getattr(frontend, "repeats_on_noise", False)


def hold_default(frontend, filt, given) -> None:
    """``filt``'s ``hold_repeats`` (where it has one) as :func:`holds_repeats` says, unless
    ``given`` (the parameters asked for) sets it."""
    if "hold_repeats" in filt.get_params() and "hold_repeats" not in given:
        filt.set_params(hold_repeats=holds_repeats(frontend))


def _construct(cls, params: dict, rng):
    obj = cls()
    obj.set_params(**params)
    if "random_state" in obj.get_params() and "random_state" not in params:
        obj.set_params(random_state=rng)
    return obj


@dataclass
class Method:
    """A fitted or unfitted front end + optional temporal filter.

    ``fit`` trains on the reference images only; ``score`` returns the
    (filtered) score matrix of the queries and records timings in ``timing_``.

    ``seed`` and ``seeded`` (set by :func:`make_method` from an int ``random_state``): every
    ``fit`` first gives the parts named in ``seeded`` (``"frontend"``, ``"filter"``; those
    still holding a Generator) one new Generator seeded with ``seed``, so that refitting gives
    the same map.
    """

    name: str
    frontend: Encoder
    filter: TemporalFilter | None = None
    timing_: dict = field(default_factory=dict)
    seed: int | None = field(default=None, repr=False)
    seeded: tuple[str, ...] = field(default=(), repr=False)

    def fit(self, reference_images) -> Method:
        """Fit the front end, then the filter on the reference traverse's own scores."""
        return self._fit_checked(reference_images, None)

    def _fit_checked(self, reference_images, map_chunks) -> Method:
        """:meth:`fit`, the front end's per-image work run through ``map_chunks`` when it is
        not None (see :meth:`flyvpr.frontends.base.Encoder._fit_chunks`)."""
        t0 = time.perf_counter()
        if self.seed is not None and self.seeded:
            rng = np.random.default_rng(self.seed)  # as make_method made it: the same map
            for part in self.seeded:
                obj = getattr(self, part)
                # (unless the part was since given a seed of its own)
                if isinstance(obj.get_params().get("random_state"), np.random.Generator):
                    obj.set_params(random_state=rng)
        filt = self.filter
        if filt is not None and not getattr(filt, "needs_reference_scores", False):
            # an online filter checks its parameters on reset: before the front end's fit
            # (minutes on a long recording), not at the first query after the map is written
            reset = getattr(filt, "reset", None)
            if reset is not None:
                reset()
        self.frontend._fit_checked(reference_images, map_chunks)
        if self.filter is not None and getattr(self.filter, "needs_reference_scores", False):
            own = self.frontend.score(reference_images)
            try:
                self.filter.fit(own)
            except ValueError as exc:
                raise ValueError(
                    f"method {self.name!r}: its filter learns from the reference images' own "
                    f"scores ({own.shape[0]} reference images): {exc}"
                ) from exc
        self.timing_ = {"fit_s": time.perf_counter() - t0}
        return self

    def score(self, query_images) -> np.ndarray:
        """Score matrix (n_query, n_reference) of the queries, filtered if a filter is set.

        ``timing_`` gets ``encode_s`` (encoding the queries) and ``match_s``
        (scoring against the references and temporal filtering).
        """
        t0 = time.perf_counter()
        codes = self.frontend.encode(query_images)
        t1 = time.perf_counter()
        S = self.frontend.score_codes(codes)
        if self.filter is not None:
            S = self.filter.filter(S)
        t2 = time.perf_counter()
        self.timing_.update(encode_s=t1 - t0, match_s=t2 - t1)
        return S

    @property
    def train_accuracy(self) -> float | None:
        return getattr(self.frontend, "train_accuracy_", None)

    def footprint(self) -> dict:
        """Layers, trained parameters and neurons of front end + filter."""
        fp = dict(self.frontend.footprint())
        if self.filter is not None:
            extra = self.filter.footprint(self.frontend.n_reference_)
            for key in ("layers", "params", "neurons"):
                fp[key] = int(fp.get(key, 0)) + int(extra.get(key, 0))
        return {k: fp[k] for k in ("layers", "params", "neurons")}
