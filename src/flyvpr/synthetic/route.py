"""A route under several conditions: :func:`make_route` and :class:`SyntheticRoute`.

:func:`make_route` checks its arguments, builds the world once
(:mod:`~flyvpr.synthetic.world`) and renders it under every condition asked for
(:mod:`~flyvpr.synthetic.render`). The ground truth is the frame alignment
itself: frame ``i`` of every condition shows place ``i``, so
:meth:`SyntheticRoute.ground_truth` is a band of half-width ``tolerance``.

Randomness
----------
``random_state`` becomes one Generator, from which two seeds are drawn in this
order: the world seed, then the nuisance seed. The world (all geometry and
textures) comes from the world seed only, so it is shared by all conditions.
Condition ``name`` draws its nuisances from a Generator seeded with
``[nuisance seed, crc32(name)]``, in the order: viewpoint jitter, exposure
flicker, clouds, then sensor noise chunk by chunk. A condition therefore
renders the same whichever other conditions are asked for.
"""

from __future__ import annotations

import logging
import numbers
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .._validation import (
    check_fraction,
    check_positive_int,
    check_random_state,
    is_real,
)
from ..datasets import ground_truth_from_frames
from ..images import DEFAULT_SIZE
from .conditions import CONDITIONS, Condition
from .render import _render_condition
from .world import _Geometry, _make_world

__all__ = ["SyntheticRoute", "make_route"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class SyntheticRoute:
    """Frame-aligned traverses of one synthetic route under several conditions.

    Attributes
    ----------
    images : dict of str to ndarray, shape (n_places, H, W), float32 in [0, 1]
        Gray frames per condition name, in route order.
    rgb : dict of str to ndarray, shape (n_places, H, W, 3), or None
        The same frames in colour (only with ``return_rgb=True``).
    conditions : tuple of str
        Condition names in the order asked for: the first is the reference
        traverse, the second the query traverse.
    step : float
        Distance between consecutive places, as a fraction of the frame width
        (for the nearest layer).
    """

    images: dict[str, np.ndarray]
    rgb: dict[str, np.ndarray] | None
    conditions: tuple[str, ...]
    step: float

    @property
    def n_places(self) -> int:
        """Number of places (frames per condition)."""
        return int(self.images[self.conditions[0]].shape[0])

    @property
    def reference_images(self) -> np.ndarray:
        """Frames of the first condition, shape (n_places, H, W)."""
        return self.images[self.conditions[0]]

    @property
    def query_images(self) -> np.ndarray:
        """Frames of the second condition (the first if only one), shape (n_places, H, W)."""
        return self.images[self.conditions[min(1, len(self.conditions) - 1)]]

    @property
    def reference_rgb(self) -> np.ndarray | None:
        """Colour frames of the first condition, or None."""
        return None if self.rgb is None else self.rgb[self.conditions[0]]

    @property
    def query_rgb(self) -> np.ndarray | None:
        """Colour frames of the second condition, or None."""
        if self.rgb is None:
            return None
        return self.rgb[self.conditions[min(1, len(self.conditions) - 1)]]

    def ground_truth(self, tolerance: int = 0) -> np.ndarray:
        """Boolean ground truth for any pair of this route's traverses.

        Parameters
        ----------
        tolerance : int
            A reference place counts as a match when it lies within this many
            frames of the query's place (the paper uses 20 frames on Nordland).

        Returns
        -------
        ndarray of bool, shape (n_places, n_places)
            Rows are queries, columns references: ``|i - j| <= tolerance``
            (:func:`flyvpr.datasets.ground_truth_from_frames` with the place indices).

        Raises
        ------
        TypeError, ValueError
            If ``tolerance`` is not a non-negative int.
        """
        idx = np.arange(self.n_places)
        return ground_truth_from_frames(idx, idx, tolerance)


def _check_size(size) -> tuple[int, int]:
    try:
        h, w = size
    except (TypeError, ValueError):
        raise TypeError(f"size must be a pair (H, W) of ints; got {size!r}") from None
    for v in (h, w):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            raise TypeError(f"size must be a pair (H, W) of ints; got {size!r}")
    if h < 4 or w < 4:
        raise ValueError(f"size must be at least (4, 4); got {tuple(size)!r}")
    return int(h), int(w)


def _resolve_conditions(conditions) -> list[Condition]:
    if isinstance(conditions, (str, Condition)):
        conditions = (conditions,)
    try:
        items = list(conditions)
    except TypeError:
        raise TypeError(
            f"conditions must be a sequence of names or Condition objects; got {conditions!r}"
        ) from None
    if not items:
        raise ValueError("conditions is empty: expected at least one condition name")
    out = []
    for item in items:
        if isinstance(item, Condition):
            out.append(item)
        elif isinstance(item, str):
            if item not in CONDITIONS:
                raise ValueError(
                    f"unknown condition {item!r}; known conditions: {sorted(CONDITIONS)}"
                )
            out.append(CONDITIONS[item])
        else:
            raise TypeError(
                f"conditions must hold names or Condition objects; got {type(item).__name__}"
            )
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise ValueError(f"conditions must have distinct names; got {names}")
    return out


def make_route(
    n_places: int = 500,
    size=DEFAULT_SIZE,
    conditions: Sequence[str | Condition] = ("summer", "winter"),
    *,
    step: float = 0.125,
    supersample: int = 2,
    viewpoint_jitter: float = 1.0,
    return_rgb: bool = False,
    random_state=0,
) -> SyntheticRoute:
    """Render a synthetic route under several appearance conditions.

    Parameters
    ----------
    n_places : int
        Number of places along the route (frames per condition), at least 2.
    size : (int, int)
        Output image size (H, W); the paper's is (32, 64).
    conditions : sequence of str or Condition
        Names from :data:`CONDITIONS` (``'summer'``, ``'fall'``, ``'winter'``,
        ``'night'``) or :class:`Condition` objects. The first is the reference
        traverse, the second the query traverse.
    step : float
        Camera movement between places as a fraction of the frame width, for
        the nearest layer (distant layers move less); in (0, 2]. The default
        shifts the view by 1/8 of a frame per place.
    supersample : int
        Frames are rendered at ``supersample * size`` and area-averaged down.
    viewpoint_jitter : float
        Scale of the per-frame viewpoint changes (position along the route,
        yaw, pitch, zoom); 0 renders every condition from the same viewpoint.
    return_rgb : bool
        Also return the colour frames (``route.rgb``).
    random_state : None, int or numpy.random.Generator
        Seeds the world and the nuisances (see the module notes for the order
        of the draws).

    Returns
    -------
    SyntheticRoute
        ``images[name]`` has shape (n_places, H, W), float32 in [0, 1]; frame
        ``i`` of every condition shows place ``i``.

    Raises
    ------
    TypeError
        For wrong types of ``n_places``, ``size``, ``conditions``, ``random_state``,
        ``supersample``, ``step`` or ``viewpoint_jitter``.
    ValueError
        If ``n_places < 2``, ``size`` is smaller than (4, 4), ``step`` is outside
        (0, 2], ``viewpoint_jitter`` is negative, ``supersample`` is below 1,
        ``random_state`` is negative, a condition name is unknown (the message lists the
        known ones) or repeated, or a :class:`Condition` lacks a material's colour.

    Examples
    --------
    >>> route = make_route(50, conditions=("summer", "winter"), random_state=1)
    >>> route.reference_images.shape, route.query_images.dtype
    ((50, 32, 64), dtype('float32'))
    >>> route.ground_truth(tolerance=2).sum(axis=1)[:4]
    array([3, 4, 5, 5])
    """
    n_places = check_positive_int(n_places, "n_places", minimum=2)
    h, w = _check_size(size)
    supersample = check_positive_int(supersample, "supersample")
    step = check_fraction(step, "step", 0.0, 2.0)
    if not is_real(viewpoint_jitter):
        raise TypeError(f"viewpoint_jitter must be a number; got {type(viewpoint_jitter).__name__}")
    if not np.isfinite(viewpoint_jitter) or viewpoint_jitter < 0:
        raise ValueError(f"viewpoint_jitter must be a finite number >= 0; got {viewpoint_jitter}")
    conds = _resolve_conditions(conditions)
    rng = check_random_state(random_state)

    world_seed, nuisance_seed = (int(v) for v in rng.integers(0, 2**63 - 1, size=2))
    hr, wr = h * supersample, w * supersample
    geo = _Geometry(
        height=hr,
        width=wr,
        horizon=0.48 * hr,
        unit=hr / 64.0,
        step_px=step * wr,
        margin=int(np.ceil(0.25 * wr + 4 * hr / 64.0 * max(viewpoint_jitter, 1.0))),
    )
    layers = _make_world(np.random.default_rng(world_seed), geo, n_places)
    images: dict[str, np.ndarray] = {}
    rgb: dict[str, np.ndarray] | None = {} if return_rgb else None
    for cond in conds:
        cond_rng = np.random.default_rng([nuisance_seed, zlib.crc32(cond.name.encode())])
        gray, colour = _render_condition(
            cond,
            layers,
            geo,
            n_places,
            (h, w),
            supersample,
            float(viewpoint_jitter),
            cond_rng,
            return_rgb,
        )
        images[cond.name] = gray
        if rgb is not None:
            rgb[cond.name] = colour
        logger.debug("rendered condition %r: %d places at %dx%d", cond.name, n_places, h, w)
    return SyntheticRoute(
        images=images, rgb=rgb, conditions=tuple(c.name for c in conds), step=step
    )
