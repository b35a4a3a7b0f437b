"""Appearance conditions: how the same world looks in summer, fall, winter and at night.

Every pixel of the world carries a *material* label (one of :data:`MATERIALS`)
and a texture value in [0, 1]. A :class:`Condition` maps each material to two
colours (texture 0 and 1), so a season changes colours non-uniformly before
the gray conversion: green fields become snow, leaves turn orange or bare,
snow speckles the dark forest. A condition also sets the illumination (gain,
gamma), the haze over distant layers, the clouds, the per-frame exposure
flicker, the sensor noise and, at night, a headlight cone and lit windows;
:mod:`flyvpr.synthetic.render` applies them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

__all__ = ["MATERIALS", "Condition", "CONDITIONS"]

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
