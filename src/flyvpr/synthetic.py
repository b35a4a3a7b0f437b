"""A procedurally generated route: the default data set that needs no download.

The same sequence of places is rendered under several appearance conditions
(``'summer'``, ``'fall'``, ``'winter'``, ``'night'``), frame-aligned like the
Nordland traverses the paper uses (Sec. Experiments): frame ``i`` of every
condition shows place ``i``.

The world
---------
A landscape seen by a camera moving along a straight line, built from
panoramic strips at several depths (parallax layers):

* sky with per-condition clouds (the clouds are weather, not place);
* distant mountains, whose skyline comes from smoothed 1-D noise;
* a band of forest on the middle distance;
* fields (grass, crops, ploughed soil) with conifers, deciduous trees,
  farm houses (red, white, yellow, with windows) and telegraph poles placed
  along the route; forests and farms come in stretches, so some places are
  distinctive and others look much alike;
* the track bed and rails in front of the camera, the same in every frame
  (as in the Nordland footage, it makes single frames more alike).

Place ``i`` is a window of these strips at ``x = i * step`` (times each layer's
parallax), so consecutive places look alike and distant ones differ: temporal
filters have something to use and single frames stay ambiguous.

Appearance conditions
---------------------
Every pixel carries a *material* label and a texture value in [0, 1]. A
:class:`Condition` maps each material to two colours (texture 0 and 1), so the
seasons change colours non-uniformly before the gray conversion (green fields
become snow, leaves turn orange or bare, snow speckles the dark forest). On top
come haze over distant layers, global gain, gamma, per-frame exposure flicker,
a headlight cone and lit windows at night, sensor noise and a small viewpoint
jitter per frame (position along the route, yaw, pitch and zoom).

Frames are rendered at ``supersample`` times the output size in RGB, turned to
gray with the BT.601 luma weights of :func:`flyvpr.images.to_gray` and
area-averaged to ``size``, as the paper's pre-processing does for camera frames
(Sec. Data Preprocessing). Colour is looked up per (row, material, texture
level) in a table per condition, so rendering is a few gathers per pixel:
500 places in two conditions take about 0.3 s.

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
import re
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from ._io import atomic_open
from ._validation import check_fraction, check_positive_int, check_random_state
from .images import DEFAULT_SIZE, to_gray

__all__ = [
    "MATERIALS",
    "Condition",
    "CONDITIONS",
    "SyntheticRoute",
    "make_route",
    "save_route",
]

logger = logging.getLogger(__name__)

#: Material labels of the world, in label order. Each condition gives every
#: material a colour for texture value 0 and one for texture value 1.
MATERIALS = (
    "sky",
    "mountain",
    "forest",
    "grass",
    "crop",
    "soil",
    "conifer",
    "leaves",
    "trunk",
    "wall_red",
    "wall_white",
    "wall_yellow",
    "roof",
    "window",
    "pole",
    "gravel",
    "rail",
)
_M = {name: i for i, name in enumerate(MATERIALS)}
_SKY = _M["sky"]

#: How much of a condition's haze reaches each material (distance from the camera).
_HAZE_DEPTH = {"mountain": 1.0, "forest": 0.55, "sky": 0.0}

#: Render pixels handled per batch (frames while rendering, objects while
#: drawing the world): bounds the memory of the full-resolution temporaries.
_PIXELS_PER_BATCH = 2**20
#: Pattern of the file names written by :func:`save_route` (Nordland layout).
_FILE_RE = re.compile(r"^images-\d{5,}\.png$")

_RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Condition:
    """Appearance of the world under one condition (season, time of day).

    Parameters
    ----------
    name : str
        Name of the condition; also the folder name used by :func:`save_route`.
    colours : mapping of str to (rgb, rgb)
        For every name in :data:`MATERIALS`, the RGB colour (in [0, 1]) at
        texture value 0 and at texture value 1; pixels mix the two linearly.
        For ``'sky'`` the pair is (sky at the top of the image, sky at the
        horizon) and clouds are mixed in with ``cloud_colour``.
    gain : float
        Global illumination factor.
    gamma : float
        Exponent applied to the illuminated colour (above 1 darkens mid-tones).
    haze : float
        Fraction of ``haze_colour`` mixed into the most distant layer.
    haze_colour : rgb
    cloud_amount : float
        Opacity of the clouds in the sky, in [0, 1].
    cloud_colour : rgb
    exposure_std : float
        Standard deviation of the slowly varying per-frame exposure (relative).
    noise_std : float
        Standard deviation of the Gaussian sensor noise per pixel at render
        resolution (luminance noise: the same on the three channels).
    headlight : float
        Strength of a light cone on the track in front of the camera (night).
    emission : mapping of str to rgb
        Light emitted by materials (lit windows at night), added after the
        illumination and gamma.
    """

    name: str
    colours: Mapping[str, tuple[_RGB, _RGB]]
    gain: float = 1.0
    gamma: float = 1.0
    haze: float = 0.0
    haze_colour: _RGB = (0.7, 0.75, 0.8)
    cloud_amount: float = 0.3
    cloud_colour: _RGB = (0.95, 0.95, 0.95)
    exposure_std: float = 0.05
    noise_std: float = 0.02
    headlight: float = 0.0
    emission: Mapping[str, _RGB] = field(default_factory=dict)

    def _arrays(self):
        """Colour tables indexed by material label: (c0, c1 - c0, emission, haze weight)."""
        missing = [m for m in MATERIALS if m not in self.colours]
        if missing:
            raise ValueError(f"condition {self.name!r} has no colours for materials {missing}")
        c0 = np.array([self.colours[m][0] for m in MATERIALS], dtype=np.float32)
        c1 = np.array([self.colours[m][1] for m in MATERIALS], dtype=np.float32)
        emission = np.zeros((len(MATERIALS), 3), dtype=np.float32)
        for m, rgb in self.emission.items():
            if m not in _M:
                raise ValueError(
                    f"condition {self.name!r}: unknown material {m!r} in emission; "
                    f"known: {list(MATERIALS)}"
                )
            emission[_M[m]] = rgb
        haze = np.zeros(len(MATERIALS), dtype=np.float32)
        for m, w in _HAZE_DEPTH.items():
            haze[_M[m]] = w * self.haze
        return c0, c1 - c0, emission, haze


_SUMMER_COLOURS = {
    "sky": ((0.30, 0.50, 0.85), (0.72, 0.82, 0.95)),
    "mountain": ((0.22, 0.32, 0.35), (0.40, 0.48, 0.52)),
    "forest": ((0.06, 0.20, 0.07), (0.20, 0.38, 0.15)),
    "grass": ((0.22, 0.45, 0.12), (0.45, 0.65, 0.25)),
    "crop": ((0.60, 0.58, 0.25), (0.80, 0.75, 0.40)),
    "soil": ((0.30, 0.22, 0.14), (0.45, 0.35, 0.22)),
    "conifer": ((0.03, 0.15, 0.05), (0.12, 0.30, 0.10)),
    "leaves": ((0.12, 0.35, 0.08), (0.35, 0.60, 0.20)),
    "trunk": ((0.20, 0.14, 0.08), (0.35, 0.25, 0.15)),
    "wall_red": ((0.50, 0.08, 0.06), (0.65, 0.15, 0.10)),
    "wall_white": ((0.80, 0.80, 0.76), (0.92, 0.92, 0.88)),
    "wall_yellow": ((0.75, 0.62, 0.25), (0.88, 0.75, 0.38)),
    "roof": ((0.15, 0.14, 0.14), (0.30, 0.28, 0.27)),
    "window": ((0.05, 0.07, 0.10), (0.25, 0.30, 0.35)),
    "pole": ((0.25, 0.20, 0.15), (0.40, 0.33, 0.25)),
    "gravel": ((0.30, 0.28, 0.26), (0.55, 0.52, 0.48)),
    "rail": ((0.35, 0.35, 0.37), (0.70, 0.70, 0.72)),
}

_FALL_COLOURS = {
    **_SUMMER_COLOURS,
    "sky": ((0.55, 0.57, 0.60), (0.72, 0.72, 0.72)),
    "mountain": ((0.30, 0.30, 0.30), (0.42, 0.42, 0.42)),
    "forest": ((0.12, 0.16, 0.07), (0.45, 0.30, 0.10)),
    "grass": ((0.30, 0.35, 0.12), (0.50, 0.48, 0.22)),
    "crop": ((0.40, 0.32, 0.18), (0.62, 0.52, 0.30)),
    "soil": ((0.22, 0.16, 0.10), (0.35, 0.26, 0.16)),
    "leaves": ((0.55, 0.22, 0.05), (0.90, 0.60, 0.15)),
    "wall_red": ((0.42, 0.07, 0.05), (0.55, 0.12, 0.08)),
    "gravel": ((0.22, 0.20, 0.19), (0.42, 0.40, 0.37)),
}

_WINTER_COLOURS = {
    **_SUMMER_COLOURS,
    "sky": ((0.62, 0.68, 0.78), (0.82, 0.85, 0.90)),
    "mountain": ((0.55, 0.58, 0.62), (0.92, 0.93, 0.96)),
    "forest": ((0.10, 0.13, 0.12), (0.85, 0.87, 0.90)),
    "grass": ((0.82, 0.84, 0.88), (0.95, 0.96, 0.98)),
    # Stubble and ploughed soil hold the snow less evenly than grass: the
    # field edges stay faintly visible, as on real winter footage.
    "crop": ((0.62, 0.60, 0.52), (0.95, 0.96, 0.98)),
    "soil": ((0.30, 0.27, 0.25), (0.92, 0.93, 0.95)),
    "conifer": ((0.05, 0.10, 0.08), (0.80, 0.82, 0.85)),
    "leaves": ((0.25, 0.22, 0.20), (0.55, 0.55, 0.56)),
    "roof": ((0.80, 0.82, 0.86), (0.95, 0.96, 0.98)),
    "gravel": ((0.45, 0.45, 0.47), (0.88, 0.89, 0.92)),
    "rail": ((0.15, 0.15, 0.17), (0.40, 0.40, 0.42)),
}

#: Named conditions. Use :func:`dataclasses.replace` on one of them to make a
#: variant, e.g. ``dataclasses.replace(CONDITIONS['winter'], name='storm', noise_std=0.08)``.
CONDITIONS: dict[str, Condition] = {
    "summer": Condition(
        "summer",
        _SUMMER_COLOURS,
        gain=1.0,
        haze=0.35,
        haze_colour=(0.70, 0.78, 0.90),
        cloud_amount=0.45,
        exposure_std=0.05,
        noise_std=0.02,
    ),
    "fall": Condition(
        "fall",
        _FALL_COLOURS,
        gain=0.85,
        gamma=1.1,
        haze=0.5,
        haze_colour=(0.65, 0.66, 0.68),
        cloud_amount=0.7,
        cloud_colour=(0.45, 0.46, 0.48),
        exposure_std=0.08,
        noise_std=0.03,
    ),
    "winter": Condition(
        "winter",
        _WINTER_COLOURS,
        gain=0.8,
        gamma=1.15,
        haze=0.6,
        haze_colour=(0.80, 0.82, 0.86),
        cloud_amount=0.6,
        cloud_colour=(0.60, 0.62, 0.66),
        exposure_std=0.10,
        noise_std=0.03,
    ),
    "night": Condition(
        "night",
        {
            **_SUMMER_COLOURS,
            "sky": ((0.01, 0.01, 0.03), (0.05, 0.05, 0.09)),
        },
        gain=0.10,
        gamma=1.0,
        haze=0.0,
        cloud_amount=0.2,
        cloud_colour=(0.10, 0.10, 0.12),
        exposure_std=0.10,
        noise_std=0.05,
        headlight=6.0,
        emission={"window": (0.85, 0.70, 0.30)},
    ),
}


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
            Rows are queries, columns references: ``|i - j| <= tolerance``.

        Raises
        ------
        TypeError, ValueError
            If ``tolerance`` is not a non-negative int.
        """
        if isinstance(tolerance, bool) or not isinstance(tolerance, numbers.Integral):
            raise TypeError(f"tolerance must be an int; got {type(tolerance).__name__}")
        if tolerance < 0:
            raise ValueError(f"tolerance must be >= 0 frames; got {tolerance}")
        idx = np.arange(self.n_places)
        return np.abs(idx[:, None] - idx[None, :]) <= int(tolerance)


# -- noise ------------------------------------------------------------------------------------


def _smoothstep(f: np.ndarray) -> np.ndarray:
    return f * f * (3.0 - 2.0 * f)


def _noise_1d(rng: np.random.Generator, n: int, scales, weights) -> np.ndarray:
    """Smooth value noise of length ``n`` in [0, 1]: octaves of interpolated random values."""
    x = np.arange(n, dtype=np.float64)
    out = np.zeros(n, dtype=np.float64)
    for scale, weight in zip(scales, weights, strict=True):
        pos = x / max(float(scale), 1e-6)
        i = pos.astype(np.int64)
        f = _smoothstep(pos - i)
        ctrl = rng.random(int(i[-1]) + 2)
        out += weight * (ctrl[i] * (1.0 - f) + ctrl[i + 1] * f)
    return out / float(sum(weights))


def _noise_2d(rng: np.random.Generator, shape, cells, weights) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1]; ``cells`` are (cell_y, cell_x) per octave."""
    h, w = shape
    out = np.zeros((h, w), dtype=np.float32)
    for (cell_y, cell_x), weight in zip(cells, weights, strict=True):
        py = np.arange(h) / max(float(cell_y), 1e-6)
        px = np.arange(w) / max(float(cell_x), 1e-6)
        iy, ix = py.astype(np.int64), px.astype(np.int64)
        fy = _smoothstep(py - iy).astype(np.float32)[:, None]
        fx = _smoothstep(px - ix).astype(np.float32)[None, :]
        ctrl = rng.random((int(iy[-1]) + 2, int(ix[-1]) + 2), dtype=np.float32)
        top = ctrl[iy][:, ix] * (1 - fx) + ctrl[iy][:, ix + 1] * fx
        bottom = ctrl[iy + 1][:, ix] * (1 - fx) + ctrl[iy + 1][:, ix + 1] * fx
        out += weight * (top * (1 - fy) + bottom * fy)
    return out / np.float32(sum(weights))


def _encode(labels: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """Pack a label (high byte) and an 8-bit texture value (low byte) into int16."""
    t8 = np.clip(np.rint(texture * 255.0), 0, 255).astype(np.int16)
    return (labels.astype(np.int16) << 8) | t8


# -- the world --------------------------------------------------------------------------------


@dataclass
class _Layer:
    parallax: float
    codes: np.ndarray  # int16 (Hr, L): label << 8 | texture, -1 where transparent


@dataclass
class _Geometry:
    height: int  # render rows
    width: int  # render columns
    horizon: float  # row of the horizon
    unit: float  # render pixels per pixel of a 64-row image: keeps textures resolution-free
    step_px: float  # camera movement per place at parallax 1, in render pixels
    margin: int  # extra strip columns on each side for jitter and zoom


def _strip_width(geo: _Geometry, n_places: int, parallax: float) -> int:
    return int(np.ceil((n_places - 1) * geo.step_px * parallax)) + geo.width + 2 * geo.margin


def _texture(rng, geo: _Geometry, width: int, fine: float = 1.0) -> np.ndarray:
    u = geo.unit
    return _noise_2d(
        rng,
        (geo.height, width),
        cells=[(fine * u, fine * u), (3 * u, 4 * u), (8 * u, 12 * u)],
        weights=[0.5, 0.3, 0.2],
    )


def _rasterise(keys, shape_fn, cx, base, half_width, height, variant, priority) -> None:
    """Draw K objects into ``keys`` (int32 (Hr, L)), nearer objects winning.

    Every pixel of object k gets the key ``priority[k] << 8 | label``; a pixel
    keeps the largest key written to it, so the drawing order does not matter.
    ``shape_fn(u, v, variant)`` maps normalised coordinates (u: -1..1 across the
    object, v: 0 at the base to 1 at the top) to a label, -1 outside.
    """
    if cx.size == 0:
        return
    h_rows, n_cols = keys.shape
    box_w = 2 * int(np.ceil(half_width.max())) + 1
    box_h = int(np.ceil(height.max())) + 1
    # Objects go in batches of bounding boxes so large renders stay within memory.
    batch = max(1, _PIXELS_PER_BATCH // (box_w * box_h))
    for lo in range(0, cx.size, batch):
        k = slice(lo, lo + batch)
        x0, y0 = cx[k, None, None], base[k, None, None]
        cols = np.rint(x0).astype(np.int64) + (np.arange(box_w) - box_w // 2)[None, None]
        rows = np.rint(y0).astype(np.int64) - np.arange(box_h)[None, :, None]
        u = (cols - x0) / half_width[k, None, None]
        v = (y0 - rows) / height[k, None, None]
        labels = shape_fn(u, v, variant[k, None, None])
        cols, rows = np.broadcast_arrays(cols, rows)
        inside = (labels >= 0) & (rows >= 0) & (rows < h_rows) & (cols >= 0) & (cols < n_cols)
        flat = rows[inside] * n_cols + cols[inside]
        prio = np.broadcast_to(priority[k, None, None], labels.shape)[inside]
        np.maximum.at(keys.reshape(-1), flat, ((prio << 8) | labels[inside]).astype(np.int32))


def _conifer(u, v, variant):
    # Tiered silhouette: the width shrinks towards the top with a saw-tooth per tier.
    tiers = 0.65 + 0.35 * ((1.0 - v) * 4.0 % 1.0)
    foliage = (v >= 0.08) & (v <= 1.0) & (np.abs(u) <= (1.0 - v) * tiers)
    trunk = (v >= 0) & (v < 0.12) & (np.abs(u) < 0.15)
    return np.where(foliage, _M["conifer"], np.where(trunk, _M["trunk"], -1))


def _deciduous(u, v, variant):
    canopy = u**2 + ((v - 0.62) / 0.38) ** 2 <= 1.0
    trunk = (v >= 0) & (v < 0.5) & (np.abs(u) < 0.12)
    return np.where(canopy, _M["leaves"], np.where(trunk, _M["trunk"], -1))


def _house(u, v, variant):
    wall_label = _M["wall_red"] + variant  # variant 0, 1, 2: red, white, yellow
    wall = (v >= 0) & (v < 0.55) & (np.abs(u) <= 1.0)
    roof = (v >= 0.55) & (v <= 1.0) & (np.abs(u) <= 1.15 * (1.0 - v) / 0.45)
    window = wall & (v > 0.18) & (v < 0.40) & (((u + 1.0) * 2.0) % 1.0 > 0.35) & (np.abs(u) < 0.9)
    return np.where(
        window, _M["window"], np.where(wall, wall_label, np.where(roof, _M["roof"], -1))
    )


def _pole(u, v, variant):
    mast = (v >= 0) & (v <= 1.0) & (np.abs(u) < 0.2)
    bar = (v >= 0.86) & (v <= 0.91) & (np.abs(u) <= 1.0)
    return np.where(mast | bar, _M["pole"], -1)


def _make_world(rng: np.random.Generator, geo: _Geometry, n_places: int) -> list[_Layer]:
    """Build the parallax layers, far to near (the sky comes per condition)."""
    hr, wr, u = geo.height, geo.width, geo.unit
    rows = np.arange(hr, dtype=np.float64)[:, None]
    layers = []

    # Distant mountains: a skyline from three octaves of smooth noise.
    width = _strip_width(geo, n_places, 0.15)
    relief = _noise_1d(rng, width, [wr, wr / 3, wr / 10], [0.6, 0.3, 0.1])
    skyline = geo.horizon - hr * (0.05 + 0.30 * relief)
    mask = (rows >= skyline[None, :]) & (rows <= geo.horizon + 1)
    codes = _encode(np.full((hr, width), _M["mountain"]), _texture(rng, geo, width))
    layers.append(_Layer(0.15, np.where(mask, codes, np.int16(-1))))

    # Forest band in the middle distance, with a ragged tree line and clearings.
    width = _strip_width(geo, n_places, 0.45)
    band = _noise_1d(rng, width, [wr * 0.8, wr / 4], [0.7, 0.3])
    ragged = _noise_1d(rng, width, [1.5 * u], [1.0])
    top = geo.horizon - hr * (0.14 * np.clip(band * 1.6 - 0.45, 0.0, 1.0) + 0.04 * ragged)
    mask = (rows >= top[None, :]) & (rows <= geo.horizon + 2)
    codes = _encode(np.full((hr, width), _M["forest"]), _texture(rng, geo, width, fine=0.7))
    layers.append(_Layer(0.45, np.where(mask, codes, np.int16(-1))))

    # Near layer: fields in two distance bands, then objects drawn over them.
    width = _strip_width(geo, n_places, 1.0)
    field_kinds = np.array([_M["grass"], _M["crop"], _M["soil"]])
    split = geo.horizon + 0.12 * hr
    ground = np.full((hr, width), -1, dtype=np.int64)
    for band_rows in (rows[:, 0] >= geo.horizon, rows[:, 0] >= split):
        n_fields = int(np.ceil(width / (0.3 * wr))) + 1
        edges = np.cumsum(rng.exponential(0.8 * wr, n_fields))
        kinds = rng.choice(field_kinds, size=n_fields + 1, p=[0.55, 0.25, 0.2])
        which = np.searchsorted(edges, np.arange(width))
        ground[band_rows] = kinds[which][None, :]
    keys = np.where(ground >= 0, ground, -1).astype(np.int32)

    # Land use along the route: forest stretches alternate with open farmland.
    forest = np.clip((_noise_1d(rng, width, [2.0 * wr, wr / 2], [0.7, 0.3]) - 0.45) * 4.0, 0, 1)
    objects = []  # (shape_fn, cx, base, half_width, height, variant)
    near_lo, near_hi = geo.horizon + 0.04 * hr, geo.horizon + 0.30 * hr

    def depth_scale(base):
        # Perspective: things standing lower in the image are nearer, so larger.
        return (base - geo.horizon + 0.08 * hr) / (0.38 * hr)

    def thinned(spacing, accept):
        x = rng.uniform(0, width, int(np.ceil(width / spacing)))
        return x[rng.random(x.size) < accept(x)]

    cx = thinned(3.0 * u, lambda x: forest[x.astype(np.int64)])
    base = rng.uniform(near_lo, near_hi, cx.size)
    height = depth_scale(base) * hr * rng.uniform(0.3, 0.5, cx.size)
    objects.append((_conifer, cx, base, height * rng.uniform(0.2, 0.3, cx.size), height, 0))

    cx = thinned(12.0 * u, lambda x: 0.1 + 0.3 * (1.0 - forest[x.astype(np.int64)]))
    base = rng.uniform(near_lo, near_hi, cx.size)
    height = depth_scale(base) * hr * rng.uniform(0.22, 0.38, cx.size)
    objects.append((_deciduous, cx, base, height * rng.uniform(0.3, 0.45, cx.size), height, 0))

    # Farms: clusters of one to three houses, mostly in open land.
    farms = thinned(1.0 * wr, lambda x: 0.7 * (1.0 - forest[x.astype(np.int64)]))
    n_houses = rng.integers(1, 4, farms.size)
    cx = farms[:, None] + rng.normal(0.0, 0.12 * wr, (farms.size, 3))
    keep = np.arange(3)[None, :] < n_houses[:, None]
    cx = cx[keep]
    base = rng.uniform(near_lo, geo.horizon + 0.22 * hr, cx.size)
    height = depth_scale(base) * hr * rng.uniform(0.16, 0.26, cx.size)
    variant = rng.integers(0, 3, cx.size)
    objects.append((_house, cx, base, height * rng.uniform(0.8, 1.5, cx.size), height, variant))

    # Telegraph poles beside the track at an almost regular spacing: a repeated
    # pattern that makes places look alike.
    gaps = 0.45 * wr * (1.0 + rng.normal(0.0, 0.05, int(np.ceil(width / (0.4 * wr))) + 1))
    cx = np.cumsum(gaps) - rng.uniform(0, 0.45 * wr)
    cx = cx[(cx > 0) & (cx < width)]
    base = np.full(cx.size, geo.horizon + 0.33 * hr)
    height = np.full(cx.size, 0.55 * hr)
    objects.append((_pole, cx, base, np.full(cx.size, 0.07 * hr), height, 0))

    # Nearer objects (lower base) are drawn over farther ones.
    all_base = np.concatenate([o[2] for o in objects])
    priority = np.empty(all_base.size, dtype=np.int64)
    priority[np.argsort(all_base, kind="stable")] = np.arange(1, all_base.size + 1)
    start = 0
    for shape_fn, cx, base, half_width, height, variant in objects:
        variant = np.broadcast_to(np.asarray(variant, dtype=np.int64), cx.shape)
        stop = start + cx.size
        _rasterise(
            keys,
            shape_fn,
            cx,
            base,
            np.maximum(half_width, 0.5),
            np.maximum(height, 1.0),
            variant,
            priority[start:stop],
        )
        start = stop
    labels = np.where(keys >= 0, keys & 0xFF, -1)
    codes = _encode(np.maximum(labels, 0), _texture(rng, geo, width))
    layers.append(_Layer(1.0, np.where(labels >= 0, codes, np.int16(-1))))

    # Track bed and rails in front of the camera: the same in every frame.
    width = wr + 2 * geo.margin
    col = np.arange(width, dtype=np.float64)[None, :] - (width - 1) / 2.0
    depth = np.clip((rows - geo.horizon) / (hr - geo.horizon), 0.0, None)
    half_bed = 0.01 * wr + 0.30 * wr * depth
    gauge = 0.006 * wr + 0.17 * wr * depth
    rail_w = 0.35 * u + 0.012 * wr * depth
    labels = np.where(np.abs(col) <= half_bed, _M["gravel"], -1)
    labels = np.where((np.abs(np.abs(col) - gauge) <= rail_w) & (depth > 0), _M["rail"], labels)
    labels = np.where(rows > geo.horizon, labels, -1)
    codes = _encode(np.maximum(labels, 0), _texture(rng, geo, width, fine=0.5))
    layers.append(_Layer(0.0, np.where(labels >= 0, codes, np.int16(-1))))
    return layers


# -- rendering --------------------------------------------------------------------------------


def _colour_table(cond: Condition, geo: _Geometry, src_rows: int) -> np.ndarray:
    """Tone-mapped colour of every (source row, material, texture level), before exposure.

    Returns an array (Hr * n_materials * 256, 3): the index of a pixel is its
    packed code (label << 8 | texture) plus ``row * n_materials * 256``. Only
    the sky depends on the row (its gradient); a table makes every later step
    one gather per pixel instead of several passes over the frames.
    """
    c0, dc, _, haze_w = cond._arrays()
    t = np.arange(256, dtype=np.float32) / np.float32(255.0)
    colour = c0[:, None, :] + dc[:, None, :] * t[None, :, None]  # (n_mat, 256, 3)
    table = np.broadcast_to(colour, (src_rows, *colour.shape)).copy()
    # Sky: gradient from the top of the image to the horizon, clouds mixed in by texture.
    frac = np.clip(np.arange(src_rows, dtype=np.float32) / max(geo.horizon, 1.0), 0.0, 1.0)
    grad = c0[_SKY][None, :] + dc[_SKY][None, :] * frac[:, None]  # (Hr, 3)
    cloud = np.asarray(cond.cloud_colour, dtype=np.float32)
    alpha = np.float32(cond.cloud_amount) * t[None, :, None]
    table[:, _SKY] = grad[:, None, :] + (cloud - grad)[:, None, :] * alpha
    # Haze: distant layers fade towards the haze colour.
    haze = haze_w[None, :, None, None]
    table += (np.asarray(cond.haze_colour, dtype=np.float32) - table) * haze
    # Gain and gamma: (gain * exposure * light * c) ** gamma factors into
    # c ** gamma times per-frame and per-pixel factors applied later.
    np.clip(table, 0.0, 1.0, out=table)
    if cond.gamma != 1.0:
        table **= np.float32(cond.gamma)
    return table.reshape(-1, 3)


def _render_condition(
    cond: Condition,
    layers: list[_Layer],
    geo: _Geometry,
    n_places: int,
    size: tuple[int, int],
    supersample: int,
    jitter: float,
    rng: np.random.Generator,
    return_rgb: bool,
):
    """Render one condition: gray (n_places, H, W) and optionally RGB (n_places, H, W, 3).

    The gray image is the BT.601 luma of the unclipped colour frame, then
    clipped (what :func:`flyvpr.images.to_gray` does); the sensor noise is
    luminance noise, the same on all three channels, so the gray frames do not
    depend on whether colour is asked for.
    """
    hr, wr, u = geo.height, geo.width, geo.unit
    gamma = np.float32(cond.gamma)

    # Nuisances, drawn in the documented order: viewpoint, exposure, clouds, noise.
    # At jitter 1 the camera stands 1/10 of the place spacing off its place
    # (std) and turns by about half an output pixel: enough to hurt pixel-wise
    # matching, as real repeated traverses do.
    along = rng.normal(0.0, 0.1 * geo.step_px * jitter, n_places)
    yaw = rng.normal(0.0, 0.5 * u * jitter, n_places)
    pitch = rng.normal(0.0, 0.5 * u * jitter, n_places)
    zoom = np.exp(rng.normal(0.0, 0.01 * jitter, n_places))
    flicker = 2.0 * _noise_1d(rng, n_places, [8.0], [1.0]) - 1.0
    exposure = (cond.gain * (1.0 + 1.7 * cond.exposure_std * flicker)) ** gamma
    exposure = exposure.astype(np.float32)
    sky_width = _strip_width(geo, n_places, 0.05)
    clouds = _noise_2d(rng, (hr, sky_width), [(6 * u, 20 * u), (2 * u, 6 * u)], [0.7, 0.3])
    clouds = np.clip((clouds - 0.45) * 3.0, 0.0, 1.0)
    sky = _Layer(0.05, _encode(np.full((hr, sky_width), _SKY), clouds))

    table = _colour_table(cond, geo, hr)
    luma = to_gray(np.eye(3, dtype=np.float32)[None])[0]  # the weights to_gray uses
    table_gray = table @ luma
    row_stride = len(MATERIALS) * 256
    _, _, emission, _ = cond._arrays()
    emit = bool(emission.any())
    emission_gray = emission @ luma

    light = None
    if cond.headlight > 0:
        # A light cone on the ground in front of the camera (night).
        ys = np.arange(hr, dtype=np.float32)[:, None]
        xs = np.arange(wr, dtype=np.float32)[None, :] - (wr - 1) / 2.0
        cone = np.exp(-((xs / (0.25 * wr)) ** 2) - ((hr - 1 - ys) / (0.35 * hr)) ** 2)
        light = ((1.0 + cond.headlight * cone * (ys > geo.horizon)) ** gamma).astype(np.float32)
    noise_std = np.float32(cond.noise_std)

    h, w = size
    s = supersample
    gray = np.empty((n_places, h, w), dtype=np.float32)
    rgb_out = np.empty((n_places, h, w, 3), dtype=np.float32) if return_rgb else None
    out_y = np.arange(hr, dtype=np.float64) - (hr - 1) / 2.0
    out_x = np.arange(wr, dtype=np.float64) - (wr - 1) / 2.0
    chunk = max(1, _PIXELS_PER_BATCH // (hr * wr))
    for start in range(0, n_places, chunk):
        sl = slice(start, min(start + chunk, n_places))
        n = sl.stop - sl.start
        z = zoom[sl, None]
        src_rows = np.rint((hr - 1) / 2.0 + out_y[None] / z + pitch[sl, None])
        src_rows = np.clip(src_rows, 0, hr - 1).astype(np.int64)  # (n, Hr)
        pos = np.arange(sl.start, sl.stop) * geo.step_px + along[sl]
        view_x = (wr - 1) / 2.0 + out_x[None] / z + yaw[sl, None] + geo.margin

        codes = None
        for layer in (sky, *layers):
            n_cols = layer.codes.shape[1]
            cols = np.clip(np.rint(view_x + pos[:, None] * layer.parallax), 0, n_cols - 1)
            flat = src_rows[:, :, None] * n_cols + cols.astype(np.int64)[:, None, :]
            g = np.take(layer.codes, flat)  # (n, Hr, Wr)
            codes = g if codes is None else np.where(g >= 0, g, codes)

        idx = codes.astype(np.int64) + (src_rows * row_stride)[:, :, None]
        scale = exposure[sl, None, None]
        if light is not None:
            scale = scale * light[None]
        noise = rng.standard_normal(codes.shape, dtype=np.float32) * noise_std
        labels = codes >> 8 if emit else None

        g = np.take(table_gray, idx) * scale
        if emit:
            g += np.take(emission_gray, labels)
        g += noise
        np.clip(g, 0.0, 1.0, out=g)
        # With an integer factor the mean of each s x s block is exactly the
        # area resize of flyvpr.images.resize_area.
        gray[sl] = g.reshape(n, h, s, w, s).mean(axis=(2, 4))
        if rgb_out is not None:
            img = np.take(table, idx, axis=0) * scale[..., None]
            if emit:
                img += np.take(emission, labels, axis=0)
            img += noise[..., None]
            np.clip(img, 0.0, 1.0, out=img)
            rgb_out[sl] = img.reshape(n, h, s, w, s, 3).mean(axis=(2, 4))
    return gray, rgb_out


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
        For wrong types of ``n_places``, ``size``, ``conditions`` or ``random_state``.
    ValueError
        If ``n_places < 2``, ``size`` is smaller than (4, 4), ``step`` is outside
        (0, 2], ``viewpoint_jitter`` is negative, or a condition name is unknown
        (the message lists the known ones) or repeated.

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
    if isinstance(viewpoint_jitter, bool) or not isinstance(viewpoint_jitter, numbers.Real):
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
    images, rgb = {}, ({} if return_rgb else None)
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


# -- files ------------------------------------------------------------------------------------


def _save_png_atomic(array: np.ndarray, path: Path) -> None:
    data = np.clip(np.rint(array * 255.0), 0, 255).astype(np.uint8)
    with atomic_open(path, "wb") as fh:
        Image.fromarray(data).save(fh, format="PNG")


def save_route(
    route: SyntheticRoute, folder, *, rgb: bool | None = None, overwrite: bool = False
) -> dict[str, list[Path]]:
    """Write a route as 8-bit PNGs in the Nordland layout.

    Files are ``<folder>/<condition>/images-00000.png``, ``images-00001.png``,
    ...: one folder per condition, the same file name for the same place.

    Parameters
    ----------
    route : SyntheticRoute
    folder : str or Path
        Created if missing.
    rgb : bool, optional
        Write colour PNGs (needs a route made with ``return_rgb=True``); by
        default colour when the route has it, gray otherwise.
    overwrite : bool
        Replace earlier ``images-NNNNN.png`` files of a condition folder
        (all of them, so no stale frame of a longer route is left behind);
        other files are never touched.

    Returns
    -------
    dict of str to list of Path
        The files written per condition, in route order.

    Raises
    ------
    TypeError
        If ``route`` is not a :class:`SyntheticRoute`.
    ValueError
        If ``rgb=True`` and the route has no colour frames.
    FileExistsError
        If a condition folder already holds route images and ``overwrite`` is False.
    """
    if not isinstance(route, SyntheticRoute):
        raise TypeError(f"route must be a SyntheticRoute; got {type(route).__name__}")
    if rgb is None:
        rgb = route.rgb is not None
    elif rgb and route.rgb is None:
        raise ValueError("rgb=True needs a route made with make_route(..., return_rgb=True)")
    folder = Path(folder)
    targets = {name: folder / name for name in route.conditions}
    # Check every folder before writing anything, so a refusal leaves no half-written route.
    for sub in targets.values():
        if sub.is_dir():
            existing = [p for p in sub.iterdir() if _FILE_RE.match(p.name)]
            if existing and not overwrite:
                raise FileExistsError(
                    f"{sub} already holds {len(existing)} route images; "
                    "pass overwrite=True to replace them"
                )
    written = {}
    for name, sub in targets.items():
        sub.mkdir(parents=True, exist_ok=True)
        for p in sub.iterdir():
            if _FILE_RE.match(p.name):
                p.unlink()
        frames = route.rgb[name] if rgb else route.images[name]
        paths = []
        for i, frame in enumerate(frames):
            path = sub / f"images-{i:05d}.png"
            _save_png_atomic(frame, path)
            paths.append(path)
        written[name] = paths
    return written
