"""The world: parallax layers of material labels and textures along a straight route.

A landscape seen by a camera moving along a straight line, built from
panoramic strips at several depths (parallax layers):

* distant mountains, whose skyline comes from smoothed 1-D noise;
* a band of forest on the middle distance;
* fields (grass, crops, ploughed soil) with conifers, deciduous trees,
  farm houses (red, white, yellow, with windows) and telegraph poles placed
  along the route; forests and farms come in stretches, so some places are
  distinctive and others look much alike;
* the track bed and rails in front of the camera, the same in every frame
  (as in the Nordland footage, it makes single frames more alike).

The sky with its clouds is weather, not place: :mod:`flyvpr.synthetic.render`
draws it per condition. Place ``i`` is a window of these strips at
``x = i * step`` (times each layer's parallax), so consecutive places look
alike and distant ones differ: temporal filters have something to use and
single frames stay ambiguous.

A strip stores per pixel a packed int16 code, ``label << 8 | texture`` (an
8-bit texture value), or -1 where the layer is transparent. The world depends
only on its Generator, so every condition shows the same places.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .conditions import _M

#: Render pixels handled per batch (frames while rendering, objects while
#: drawing the world): bounds the memory of the full-resolution temporaries.
_PIXELS_PER_BATCH = 2**20


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
