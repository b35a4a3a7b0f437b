"""Dataset loaders: one module per folder layout, and a registry name -> loader.

Every loader returns a :class:`Benchmark`: a reference and a query
:class:`Traverse` plus the boolean ground truth (n_query, n_reference).
The CLI lists :data:`DATASETS` (``flyvpr datasets``) and builds its options
from each spec's ``options``.

Examples
--------
>>> sorted(DATASETS)
['generic', 'nordland', 'robotcar', 'vprbench']
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field

from . import generic, nordland, robotcar, vprbench
from .base import Benchmark, Traverse, ground_truth_from_frames, ground_truth_from_positions
from .generic import load_generic
from .nordland import load_nordland
from .robotcar import load_robotcar
from .vprbench import load_vprbench

__all__ = [
    "DATASETS",
    "DatasetSpec",
    "Benchmark",
    "Traverse",
    "ground_truth_from_frames",
    "ground_truth_from_positions",
    "load_benchmark",
    "load_generic",
    "load_nordland",
    "load_robotcar",
    "load_vprbench",
]


@dataclass(frozen=True)
class DatasetSpec:
    """What the CLI needs to know about one loader.

    Attributes
    ----------
    loader : callable
        ``loader(**options) -> Benchmark``.
    description : str
        One line for ``flyvpr datasets``.
    layout : str
        The folder layout the loader expects (several lines).
    options : tuple of str
        The loader's keyword arguments the CLI may pass (each is a parameter
        of ``loader``).
    requires : dict
        Option -> the option it needs (``radius`` needs ``positions_csv``).
    conflicts : tuple of pairs
        Options that cannot be given together.
    """

    loader: Callable[..., Benchmark]
    description: str
    layout: str
    options: tuple[str, ...]
    requires: dict = field(default_factory=dict)
    conflicts: tuple[tuple[str, str], ...] = ()

    def required_options(self) -> tuple[str, ...]:
        """Options the loader has no default for (``root`` for most layouts)."""
        params = inspect.signature(self.loader).parameters
        return tuple(o for o in self.options if params[o].default is inspect.Parameter.empty)

    def check_options(self, given, name=str) -> None:
        """Raise ValueError naming the options if ``given`` breaks a rule of this layout.

        Parameters
        ----------
        given : iterable of str
            The options set (loader keyword names).
        name : callable
            How messages show an option (the CLI passes ``radius -> --radius``).
        """
        given = set(given)
        unknown = sorted(given - set(self.options))
        if unknown:
            raise ValueError(
                f"{name(unknown[0])} does not apply to this dataset (it takes: "
                f"{', '.join(name(o) for o in self.options)})"
            )
        missing = [o for o in self.required_options() if o not in given]
        if missing:
            raise ValueError(f"{name(missing[0])} is required for this dataset")
        for option, needed in self.requires.items():
            if option in given and needed not in given:
                raise ValueError(f"{name(option)} needs {name(needed)}")
        for a, b in self.conflicts:
            if a in given and b in given:
                raise ValueError(f"{name(a)} and {name(b)} cannot be given together")


#: Registry: dataset name -> spec.  The CLI's choices come from here.
DATASETS: dict[str, DatasetSpec] = {
    "nordland": DatasetSpec(
        loader=load_nordland,
        description="Nordland railway, frame-aligned seasons; ground truth within N frames",
        layout=nordland.LAYOUT,
        options=("root", "reference", "query", "first", "count", "tolerance"),
    ),
    "robotcar": DatasetSpec(
        loader=load_robotcar,
        description=(
            "Oxford RobotCar runs (SDK layout), one frame every `spacing` metres; "
            "ground truth within tolerance_m metres"
        ),
        layout=robotcar.LAYOUT,
        options=("root", "reference", "query", "spacing", "first", "count", "tolerance_m"),
    ),
    "vprbench": DatasetSpec(
        loader=load_vprbench,
        description="a VPR-Bench dataset folder (ref/, query/, ground-truth .npy)",
        layout=vprbench.LAYOUT,
        options=("root", "trust_pickle"),
    ),
    "generic": DatasetSpec(
        loader=load_generic,
        description=(
            "two image folders matched by index (+- tolerance frames) or by a positions CSV "
            "(within radius metres)"
        ),
        layout=generic.LAYOUT,
        options=(
            "root",
            "reference",
            "query",
            "tolerance",
            "positions_csv",
            "radius",
            "first",
            "count",
        ),
        requires={"radius": "positions_csv", "positions_csv": "radius"},
        conflicts=(("tolerance", "positions_csv"),),
    ),
}


def load_benchmark(name: str, **kwargs) -> Benchmark:
    """Load the registered dataset ``name`` with the loader's keyword arguments.

    Raises
    ------
    ValueError
        If ``name`` is not registered (the message lists the known names).
    TypeError
        If a keyword is not an option of that loader (the message lists them).
    """
    if name not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; known datasets: {', '.join(sorted(DATASETS))}")
    spec = DATASETS[name]
    params = inspect.signature(spec.loader).parameters
    unknown = sorted(set(kwargs) - set(params))
    if unknown:
        raise TypeError(
            f"dataset {name!r} takes no option(s) {', '.join(unknown)}; "
            f"its options are: {', '.join(params)}"
        )
    return spec.loader(**kwargs)
