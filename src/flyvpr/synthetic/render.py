"""Camera and rendering: one condition's frames from the world's layers.

For every frame the camera stands at its place with a small viewpoint jitter
(position along the route, yaw, pitch and zoom). Frames are rendered at
``supersample`` times the output size in RGB, turned to gray with the BT.601
luma weights of :func:`flyvpr.images.to_gray` and area-averaged to ``size``,
as the paper's pre-processing does for camera frames (Sec. Data
Preprocessing). Colour is looked up per (row, material, texture level) in a
table per condition, so rendering is a few gathers per pixel: 500 places in
two conditions take about 0.3 s.

Nuisances are drawn from the condition's Generator in a fixed order:
viewpoint jitter, exposure flicker, clouds, then sensor noise chunk by chunk.
"""

from __future__ import annotations

import numpy as np

from ..images import to_gray
from .conditions import _SKY, MATERIALS, Condition
from .world import _PIXELS_PER_BATCH, _encode, _Geometry, _Layer, _noise_1d, _noise_2d, _strip_width


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
        assert codes is not None  # the sky's layer at least

        idx = codes.astype(np.int64) + (src_rows * row_stride)[:, :, None]
        scale = exposure[sl, None, None]
        if light is not None:
            scale = scale * light[None]
        noise = rng.standard_normal(codes.shape, dtype=np.float32) * noise_std
        labels = codes >> 8 if emit else None

        g = np.take(table_gray, idx) * scale
        if labels is not None:
            g += np.take(emission_gray, labels)
        g += noise
        np.clip(g, 0.0, 1.0, out=g)
        # With an integer factor the mean of each s x s block is exactly the
        # area resize of flyvpr.images.resize_area.
        gray[sl] = g.reshape(n, h, s, w, s).mean(axis=(2, 4))
        if rgb_out is not None:
            img = np.take(table, idx, axis=0) * scale[..., None]
            if labels is not None:
                img += np.take(emission, labels, axis=0)
            img += noise[..., None]
            np.clip(img, 0.0, 1.0, out=img)
            rgb_out[sl] = img.reshape(n, h, s, w, s, 3).mean(axis=(2, 4))
    return gray, rgb_out
