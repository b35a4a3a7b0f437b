"""The CANN's parameters: defaults, presets and their validation."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..._validation import check_positive_int, check_real

#: how a score row becomes the input (see the user guide's "Input")
TRANSFORMS = ("auto", "log", "linear")
#: candidate movements per frame for movement="estimate": 0.75 to 2 places in steps of 1/8
DEFAULT_VELOCITIES = (0.75, 0.875, 1.0, 1.125, 1.25, 1.375, 1.5, 1.625, 1.75, 1.875, 2.0)

#: Parameters for fast recovery after a kidnap (see "Fast recovery" in the user guide's cann-paper
#: page): ``AttractorCANN(**FAST_RECOVERY)``.  Weak attractor, strong two-timescale evidence.
FAST_RECOVERY = {
    "excitation_strength": 8.0,
    "inhibition": 1.0,
    "synaptic_time_constant": 12.0,
    "slow_time_constant": 60.0,
    "slow_fraction": 0.5,
    "input_gain": 50.0,
    "adaptation": 20.0,
    "adapt_variance": True,
    "relocation_margin": None,
}


def _optional(value, name: str, **kwargs) -> float | None:
    return None if value is None else check_real(value, name, **kwargs)


def _check_velocities(velocities, bidirectional: bool) -> np.ndarray:
    try:
        vel = np.asarray(velocities, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"velocities must be a sequence of numbers; {exc}") from exc
    if vel.ndim != 1 or vel.size == 0:
        raise ValueError(f"velocities must be a non-empty 1-d sequence; got shape {vel.shape}")
    if not np.isfinite(vel).all():
        raise ValueError(f"velocities must be finite; got {vel.tolist()}")
    if np.unique(vel).size != vel.size:
        raise ValueError(f"velocities must not repeat a value; got {vel.tolist()}")
    if bidirectional:
        # The bank spans the mirrored speeds too: a traverse driven the other way.
        vel = np.unique(np.concatenate([vel, -vel]))
    return vel


def _check_breaks(breaks) -> np.ndarray:
    """``breaks`` as int64 places, each at least 1 and each after the one before (whether each
    lies on the map is checked when the map's size is known)."""
    try:
        arr = np.asarray(breaks, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"breaks must be a sequence of place indices; {exc}") from exc
    if arr.ndim != 1:
        raise ValueError(f"breaks must be a 1-d sequence of place indices; got shape {arr.shape}")
    if arr.size and not (np.isfinite(arr).all() and (arr == np.round(arr)).all()):
        raise ValueError(f"breaks must be whole place indices; got {arr.tolist()}")
    if arr.size and (arr[0] < 1 or (np.diff(arr) <= 0).any()):
        raise ValueError(
            "breaks must be increasing place indices of at least 1 (the first place of each "
            f"stretch of the map after a break); got {arr.tolist()}"
        )
    return arr.astype(np.int64)


def check_params(est) -> dict:
    """Validate a :class:`CANN`'s constructor parameters; return them as plain numbers.

    Besides the parameters, the dict holds ``currents``: (time constant, weight) of each
    synaptic current, fast first.
    """
    p: dict[str, Any] = {
        "excitation_strength": check_real(est.excitation_strength, "excitation_strength"),
        "excitation_width": check_real(est.excitation_width, "excitation_width"),
        "inhibition": check_real(est.inhibition, "inhibition", inclusive=True),
        "tonic_inhibition": check_real(est.tonic_inhibition, "tonic_inhibition", inclusive=True),
        "threshold": check_real(est.threshold, "threshold", low=None),
        "time_constant": check_real(est.time_constant, "time_constant"),
        "synaptic_time_constant": check_real(est.synaptic_time_constant, "synaptic_time_constant"),
        "slow_time_constant": _optional(est.slow_time_constant, "slow_time_constant"),
        "slow_fraction": check_real(est.slow_fraction, "slow_fraction", inclusive=True),
        "input_gain": check_real(est.input_gain, "input_gain", inclusive=True),
        "n_steps": check_positive_int(est.n_steps, "n_steps"),
        "velocity_memory": check_real(est.velocity_memory, "velocity_memory"),
        "velocity_contrast": check_real(est.velocity_contrast, "velocity_contrast", inclusive=True),
        "adaptation": _optional(est.adaptation, "adaptation"),
        "input_clip": _optional(est.input_clip, "input_clip"),
        "relocation_floor": check_real(est.relocation_floor, "relocation_floor", low=None),
        "relocation_margin": _optional(est.relocation_margin, "relocation_margin", inclusive=True),
        "fallback_contrast": _optional(est.fallback_contrast, "fallback_contrast", inclusive=True),
        "fallback_memory": check_real(est.fallback_memory, "fallback_memory"),
    }
    if 1.0 / (p["n_steps"] * p["time_constant"]) > 1.0:
        raise ValueError(
            "n_steps * time_constant must be >= 1 so each Euler step is at most one time "
            f"constant; got n_steps={p['n_steps']}, time_constant={p['time_constant']}"
        )
    if isinstance(est.movement, str):
        if est.movement != "estimate":
            raise ValueError(f"movement must be a number or 'estimate'; got {est.movement!r}")
        p["movement"] = None
    else:
        p["movement"] = check_real(est.movement, "movement", low=None)
    for flag in ("adapt_variance", "bidirectional"):
        value = getattr(est, flag)
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"{flag} must be True or False; got {type(value).__name__}")
        p[flag] = bool(value)
    p["velocities"] = _check_velocities(est.velocities, p["bidirectional"])
    if p["slow_fraction"] > 1.0:
        raise ValueError(f"slow_fraction must be <= 1; got {p['slow_fraction']}")
    if p["slow_time_constant"] is None:
        p["currents"] = ((p["synaptic_time_constant"], 1.0),)
    else:
        p["currents"] = (
            (p["synaptic_time_constant"], 1.0 - p["slow_fraction"]),
            (p["slow_time_constant"], p["slow_fraction"]),
        )
    if est.input_transform not in TRANSFORMS:
        raise ValueError(
            f"input_transform must be one of {TRANSFORMS}; got {est.input_transform!r}"
        )
    p["input_transform"] = est.input_transform
    return p
