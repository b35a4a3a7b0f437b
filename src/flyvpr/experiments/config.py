"""Experiment configuration files: parse, validate and expand into runs.

An experiment is a TOML file with three kinds of blocks (the paper's
evaluation is ``experiments/paper.toml`` in the repository)::

    title = "FlyNet+CANN, paper reproduction"   # optional, heads the report
    description = "..."                          # optional, shown under the title

    [settings]                 # optional
    image_size = [32, 64]      # (H, W) every image is resized to (paper: 32 x 64)
    cache = true               # image cache: true (default folder), false, or a folder

    [[datasets]]               # one block per benchmark
    name = "nordland_sw"       # id the grids refer to (letters, digits, . _ -)
    loader = "nordland"        # a key of flyvpr.datasets.DATASETS
    label = "Nordland summer -> winter"   # optional, for tables and legends
    root = "../../shared/data/nordland_64x32"
    reference = "summer"       # ... every further key is an option of the loader
    query = "winter"
    first = 0
    count = 1000
    tolerance = 20

    [[grids]]                  # one block per table/figure of the report
    name = "single_frame"      # unique id
    kind = "evaluate"          # see KINDS below
    title = "Single-frame AUC" # optional heading; description = "..." optional text
    datasets = ["nordland_sw"] # names of [[datasets]] blocks
    methods = ["flynet", "fc"] # names of flyvpr.methods.METHODS
    seeds = [0, 1, 2]          # random_state of every random part (default [0])
    params = { sampling_ratio = [0.1, 0.5], epochs = 200 }
    method_params = { fc = { epochs = 100 } }   # fixed per-method values
    method_seeds = { netvlad = [0] }            # per-method seeds instead of `seeds`
    speed = 2.0                # optional: query frames kept at this speed (places/frame)
                               # or a [low, high] range drawn per frame (seeded by the seed)

Rules
-----
* **Relative paths** (``root``, ``positions_csv``, ``settings.cache``) resolve
  against the folder of the config file, never the working directory, so a
  config runs the same from anywhere.  ``experiments/paper.toml`` therefore says
  ``root = "../../shared/data/..."``: the data sits in ``shared/`` beside the
  repository.
* **Grid expansion**: the runs of a grid are the cartesian product
  datasets x methods x seeds x params.  In ``params`` a list is an axis and a
  scalar a fixed value; to pass a list as one value, wrap it: ``[[1, 2]]``.
  A key routes to the method's front end or temporal filter by constructor
  name; prefix ``frontend.`` or ``filter.`` when both take it.  A key a
  method does not take is an error (use ``method_params`` for per-method
  settings; they override ``params``).  ``random_state`` comes from ``seeds``.
* **Kinds** say what a run computes and what the report shows:

  ``evaluate``
      fit on the reference traverse, score the queries: AUC table, AUC bar
      chart, precision-recall curves (paper Figs. "FlyNet baselines" AUC and
      "PR performance").
  ``sensitivity``
      as ``evaluate`` with exactly one ``params`` axis; the report plots
      training accuracy and AUC against it (paper Sec. "Influence of
      Bio-inspiration").
  ``footprint``
      as ``evaluate``; layers/parameters/neurons table and AUC against model
      size (paper Table "FlyNet Baselines Footprint", Fig. "AUC performance vs.
      Network Size").
  ``qualitative``
      as ``evaluate``; example queries with the reference each method
      retrieved (``examples = 5`` evenly spaced queries, or ``queries = [...]``
      positions).
  ``training_curve``
      fit only; training accuracy per epoch, mean and spread over seeds (the
      front end must record ``accuracy_history_``).
  ``timing``
      as ``evaluate``, but images are decoded without the cache, a warm-up
      run on a few frames comes first (JIT compilation, first-call costs), and
      the runs execute one at a time after all others, so no other run shares
      the CPU (paper Table "Processing time comparison").

* **Run identity**: a run is (task, dataset block, method, seed, every
  front-end and filter constructor argument with defaults filled in, speed,
  image size).  Its id is a readable slug plus a hash of that spec, so the
  same run requested by two grids is computed once (spelling out a default
  value changes nothing), and an edited grid only adds the runs that are new.
  Dataset options enter as written in the file, so moving the checkout keeps
  the ids.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import numbers
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

__all__ = [
    "KINDS",
    "DatasetBlock",
    "GridBlock",
    "Settings",
    "ExperimentConfig",
    "RunSpec",
    "load_config",
    "parse_config",
]

#: grid kind -> task its runs perform (``evaluate``, ``train`` or ``timing``)
KINDS = {
    "evaluate": "evaluate",
    "sensitivity": "evaluate",
    "footprint": "evaluate",
    "qualitative": "evaluate",
    "training_curve": "train",
    "timing": "timing",
}

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_TOP_KEYS = ("title", "description", "settings", "datasets", "grids")
_SETTINGS_KEYS = ("image_size", "cache")
_GRID_KEYS = (
    "name",
    "kind",
    "title",
    "description",
    "datasets",
    "methods",
    "seeds",
    "params",
    "method_params",
    "method_seeds",
    "speed",
    "examples",
    "queries",
    "warmup",
)
#: dataset options that are file system paths (resolved against the config folder)
_PATH_OPTIONS = ("root", "positions_csv")
#: expected TOML type of each loader option, for early, precise errors
_OPTION_TYPES = {
    "root": (str,),
    "positions_csv": (str,),
    "reference": (str,),
    "query": (str,),
    "first": (int,),
    "count": (int,),
    "tolerance": (int,),
    "tolerance_m": (int, float),
    "radius": (int, float),
    "spacing": (int, float),
    "trust_pickle": (bool,),
}


def _toml_loads(text: str) -> dict:
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover - exercised on Python 3.10 only
        try:
            import tomli as tomllib
        except ImportError as exc:
            raise ImportError(
                "reading experiment configs on Python 3.10 needs tomli: pip install tomli"
            ) from exc
    return tomllib.loads(text)


def _type_name(value) -> str:
    return type(value).__name__


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


# -- blocks --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """``[settings]``: image size and image cache shared by every run."""

    image_size: tuple[int, int] = (32, 64)
    cache: bool | str = True

    def to_dict(self) -> dict:
        return {"image_size": list(self.image_size), "cache": self.cache}


@dataclass(frozen=True)
class DatasetBlock:
    """One ``[[datasets]]`` block.

    Attributes
    ----------
    name, loader, label : str
    options : dict
        Loader options as written in the file (part of the run identity).
    resolved : dict
        The same options with relative paths resolved against the config folder
        (what the loader receives).
    """

    name: str
    loader: str
    label: str
    options: dict
    resolved: dict

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "loader": self.loader,
            "label": self.label,
            "options": dict(self.options),
            "resolved": dict(self.resolved),
        }


@dataclass(frozen=True)
class GridBlock:
    """One ``[[grids]]`` block (see the module docstring for the keys)."""

    name: str
    kind: str
    title: str
    description: str
    datasets: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    params: dict
    method_params: dict
    method_seeds: dict = field(default_factory=dict)
    speed: float | tuple[float, float] | None = None
    examples: int = 5
    queries: tuple[int, ...] | None = None
    warmup: bool = True

    @property
    def task(self) -> str:
        return KINDS[self.kind]

    def seeds_for(self, method: str) -> tuple[int, ...]:
        """The seeds of ``method``: its ``method_seeds`` entry, else ``seeds``."""
        return self.method_seeds.get(method, self.seeds)

    @property
    def axes(self) -> list[str]:
        """The ``params`` keys that take several values (list-valued)."""
        return [k for k, v in self.params.items() if isinstance(v, list)]

    def param_combinations(self) -> list[dict]:
        """Every combination of the ``params`` values, in file order."""
        keys = list(self.params)
        values = [v if isinstance(v, list) else [v] for v in self.params.values()]
        return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*values)]

    def to_dict(self) -> dict:
        out = {
            k: getattr(self, k)
            for k in ("name", "kind", "title", "description", "params", "method_params")
        }
        out.update(
            datasets=list(self.datasets),
            methods=list(self.methods),
            seeds=list(self.seeds),
            speed=list(self.speed) if isinstance(self.speed, tuple) else self.speed,
            method_seeds={k: list(v) for k, v in self.method_seeds.items()},
            examples=self.examples,
            queries=None if self.queries is None else list(self.queries),
            warmup=self.warmup,
        )
        return out


@dataclass(frozen=True)
class RunSpec:
    """One run: what is hashed into its id, and what the worker needs besides.

    Attributes
    ----------
    run_id : str
        ``<task>-<dataset>-<method>-s<seed>-<hash12>``, safe as a file name.
    spec : dict
        The run's identity (JSON-serialisable): ``task``, ``dataset`` (name,
        loader, options as written), ``method``, ``seed``, ``frontend_params``,
        ``filter_params``, ``speed``, ``image_size``.
    dataset_options : dict
        Loader options with resolved paths.
    cache : bool or str
        Image cache setting (not part of the identity).
    warmup : bool
        Timing runs only: do an untimed warm-up run first.
    """

    run_id: str
    spec: dict
    dataset_options: dict
    cache: bool | str = True
    warmup: bool = True

    @property
    def task(self) -> str:
        return self.spec["task"]


def run_id_of(spec: dict) -> str:
    """Stable id of a run spec: a readable slug and 12 hex digits of its SHA-256."""
    canonical = json.dumps(spec, sort_keys=True, separators=(",", ":"), allow_nan=False)
    digest = hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:12]
    slug = f"{spec['task']}-{spec['dataset']['name']}-{spec['method']}-s{spec['seed']}"
    slug = re.sub(r"[^A-Za-z0-9._+-]", "_", slug)
    return f"{slug}-{digest}"


@dataclass(frozen=True)
class ExperimentConfig:
    """A parsed, validated experiment file.

    Attributes
    ----------
    path : Path or None
        The file it was read from.
    base_dir : Path
        Folder relative paths resolve against.
    text : str
        The file's text (copied into the results folder).
    """

    title: str
    description: str
    settings: Settings
    datasets: dict[str, DatasetBlock]
    grids: list[GridBlock]
    base_dir: Path
    text: str = ""
    path: Path | None = None

    def grid(self, name: str) -> GridBlock:
        for grid in self.grids:
            if grid.name == name:
                return grid
        raise ValueError(f"unknown grid {name!r}; grids: {', '.join(g.name for g in self.grids)}")

    def grid_runs(self, grid: GridBlock) -> list[RunSpec]:
        """The runs of one grid, in order datasets x methods x seeds x params."""
        return [item["run"] for item in self.grid_items(grid)]

    def grid_items(self, grid: GridBlock) -> list[dict]:
        """The runs of one grid with their coordinates.

        Returns
        -------
        list of dict
            Keys ``run`` (:class:`RunSpec`), ``dataset``, ``method``, ``seed``
            and ``combo`` (this run's value of every ``params`` key).
        """
        from ..methods import METHODS

        items = []
        ds_list = [self.datasets[d] for d in grid.datasets]
        coords = [
            (ds, method, seed, combo)
            for ds in ds_list
            for method in grid.methods
            for seed in grid.seeds_for(method)
            for combo in grid.param_combinations()
        ]
        for ds, method, seed, combo in coords:
            params = {**combo, **grid.method_params.get(method, {})}
            front, filt = _full_params(METHODS[method], *_route_params(METHODS[method], params))
            spec = {
                "task": grid.task,
                "dataset": {"name": ds.name, "loader": ds.loader, "options": ds.options},
                "method": method,
                "seed": seed,
                "frontend_params": front,
                "filter_params": filt,
                "speed": list(grid.speed) if isinstance(grid.speed, tuple) else grid.speed,
                "image_size": list(self.settings.image_size),
            }
            run = RunSpec(
                run_id_of(spec),
                spec,
                dict(ds.resolved),
                cache=self.settings.cache,
                warmup=grid.warmup,
            )
            items.append(
                {"run": run, "dataset": ds.name, "method": method, "seed": seed, "combo": combo}
            )
        return items

    def plan(self) -> dict[str, list[dict]]:
        """Grid name -> its runs' ids and coordinates (JSON), as stored in experiment.json.

        The report reads the plan stored at experiment time, so a later change of a
        constructor default (which changes run ids) cannot hide finished runs from it.
        """
        return {
            grid.name: [
                {
                    "run_id": item["run"].run_id,
                    "dataset": item["dataset"],
                    "method": item["method"],
                    "seed": item["seed"],
                    "combo": item["combo"],
                }
                for item in self.grid_items(grid)
            ]
            for grid in self.grids
        }

    def runs(self) -> list[RunSpec]:
        """Every distinct run of every grid (a run shared by grids appears once)."""
        seen: dict[str, RunSpec] = {}
        for grid in self.grids:
            for run in self.grid_runs(grid):
                seen.setdefault(run.run_id, run)
        return list(seen.values())

    def to_dict(self) -> dict:
        return {
            "title": self.title,
            "description": self.description,
            "settings": self.settings.to_dict(),
            "datasets": [d.to_dict() for d in self.datasets.values()],
            "grids": [g.to_dict() for g in self.grids],
            "base_dir": str(self.base_dir),
            "path": None if self.path is None else str(self.path),
        }


# -- parsing -------------------------------------------------------------------------------------
def load_config(path) -> ExperimentConfig:
    """Read and validate an experiment file.

    Parameters
    ----------
    path : str or Path
        A TOML file (see the module docstring for its schema).

    Returns
    -------
    ExperimentConfig

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        For TOML syntax errors, unknown keys, kinds, loaders, datasets or
        methods (messages name the file, the block and the known values).
    TypeError
        For values of the wrong type.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"experiment config not found: {path}")
    text = path.read_text(encoding="utf-8")
    return parse_config(text, base_dir=path.resolve().parent, source=str(path), path=path)


def parse_config(text: str, base_dir=".", source: str = "<config>", path=None) -> ExperimentConfig:
    """Parse experiment TOML text; relative paths resolve against ``base_dir``.

    See :func:`load_config`; ``source`` names the text in error messages and
    ``path`` is recorded as the config's file.
    """
    try:
        raw = _toml_loads(text)
    except ValueError as exc:  # tomllib.TOMLDecodeError is a ValueError
        raise ValueError(f"{source}: not valid TOML: {exc}") from None
    base_dir = Path(base_dir).resolve()
    _check_keys(raw, _TOP_KEYS, source)
    title = _opt_str(raw, "title", source, default="Experiment")
    description = _opt_str(raw, "description", source, default="")
    settings = _parse_settings(raw.get("settings", {}), base_dir, f"{source} [settings]")

    blocks = raw.get("datasets")
    if not isinstance(blocks, list) or not blocks:
        raise ValueError(f"{source}: expected at least one [[datasets]] block")
    datasets: dict[str, DatasetBlock] = {}
    for i, block in enumerate(blocks):
        ds = _parse_dataset(block, base_dir, f"{source} [[datasets]] #{i + 1}")
        if ds.name in datasets:
            raise ValueError(f"{source}: dataset name {ds.name!r} is used by two blocks")
        datasets[ds.name] = ds

    blocks = raw.get("grids")
    if not isinstance(blocks, list) or not blocks:
        raise ValueError(f"{source}: expected at least one [[grids]] block")
    grids: list[GridBlock] = []
    for i, block in enumerate(blocks):
        grid = _parse_grid(block, datasets, f"{source} [[grids]] #{i + 1}")
        if any(g.name == grid.name for g in grids):
            raise ValueError(f"{source}: grid name {grid.name!r} is used by two blocks")
        grids.append(grid)
    return ExperimentConfig(
        title=title,
        description=description,
        settings=settings,
        datasets=datasets,
        grids=grids,
        base_dir=base_dir,
        text=text,
        path=None if path is None else Path(path),
    )


def _check_keys(block, allowed, where: str) -> None:
    if not isinstance(block, dict):
        raise TypeError(f"{where}: expected a table; got {_type_name(block)}")
    unknown = [k for k in block if k not in allowed]
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; "
            f"allowed: {', '.join(allowed)}"
        )


def _opt_str(block: dict, key: str, where: str, default: str) -> str:
    value = block.get(key, default)
    if not isinstance(value, str):
        raise TypeError(f"{where}: {key} must be a string; got {_type_name(value)} {value!r}")
    return value


def _name(block: dict, where: str) -> str:
    if "name" not in block:
        raise ValueError(f"{where}: missing required key 'name'")
    name = block["name"]
    if not isinstance(name, str):
        raise TypeError(f"{where}: name must be a string; got {_type_name(name)} {name!r}")
    if not _NAME_RE.match(name):
        raise ValueError(
            f"{where}: name {name!r} must start with a letter or digit and hold only "
            "letters, digits, '.', '_' and '-'"
        )
    return name


def _resolve(path: str, base_dir: Path) -> str:
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else (base_dir / p).resolve())


def _parse_settings(block, base_dir: Path, where: str) -> Settings:
    _check_keys(block, _SETTINGS_KEYS, where)
    size = block.get("image_size", [32, 64])
    if not isinstance(size, list) or len(size) != 2 or not all(_is_int(v) and v > 0 for v in size):
        raise TypeError(f"{where}: image_size must be two positive ints [H, W]; got {size!r}")
    cache = block.get("cache", True)
    if isinstance(cache, str):
        cache = _resolve(cache, base_dir)
    elif not isinstance(cache, bool):
        raise TypeError(
            f"{where}: cache must be true, false or a folder path; got {_type_name(cache)}"
        )
    return Settings(image_size=(int(size[0]), int(size[1])), cache=cache)


def _parse_dataset(block, base_dir: Path, where: str) -> DatasetBlock:
    from ..datasets import DATASETS

    if not isinstance(block, dict):
        raise TypeError(f"{where}: expected a table; got {_type_name(block)}")
    name = _name(block, where)
    where = f"{where} ({name!r})"
    loader = block.get("loader")
    if loader is None:
        raise ValueError(f"{where}: missing required key 'loader'; known: {', '.join(DATASETS)}")
    if loader not in DATASETS:
        raise ValueError(
            f"{where}: unknown loader {loader!r}; known loaders: {', '.join(sorted(DATASETS))}"
        )
    label = _opt_str(block, "label", where, default=name)
    allowed = DATASETS[loader].options
    options = {k: v for k, v in block.items() if k not in ("name", "loader", "label")}
    unknown = [k for k in options if k not in allowed]
    if unknown:
        raise ValueError(
            f"{where}: loader {loader!r} takes no option(s) {', '.join(map(repr, unknown))}; "
            f"its options: {', '.join(allowed)}"
        )
    if "root" not in options:
        raise ValueError(f"{where}: missing required key 'root' (the dataset folder)")
    for key, value in options.items():
        types = _OPTION_TYPES.get(key)
        ok = types is None or (
            isinstance(value, types) and (bool in types or not isinstance(value, bool))
        )
        if not ok:
            expected = " or ".join(t.__name__ for t in types)
            raise TypeError(
                f"{where}: option {key} must be {expected}; got {_type_name(value)} {value!r}"
            )
    resolved = dict(options)
    for key in _PATH_OPTIONS:
        if key in resolved:
            resolved[key] = _resolve(resolved[key], base_dir)
    return DatasetBlock(name, loader, label, options, resolved)


def _parse_grid(block, datasets: dict, where: str) -> GridBlock:
    from ..methods import METHODS

    if not isinstance(block, dict):
        raise TypeError(f"{where}: expected a table; got {_type_name(block)}")
    _check_keys(block, _GRID_KEYS, where)
    name = _name(block, where)
    where = f"{where} ({name!r})"
    kind = block.get("kind")
    if kind not in KINDS:
        raise ValueError(f"{where}: kind must be one of {', '.join(KINDS)}; got {kind!r}")
    title = _opt_str(block, "title", where, default=name)
    description = _opt_str(block, "description", where, default="")

    ds_names = _str_list(block, "datasets", where)
    for d in ds_names:
        if d not in datasets:
            raise ValueError(
                f"{where}: unknown dataset {d!r}; [[datasets]] blocks: {', '.join(datasets)}"
            )
    methods = _str_list(block, "methods", where)
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"{where}: unknown method {m!r}; known methods: {', '.join(METHODS)}")
    seeds = _check_seeds(block.get("seeds", [0]), f"{where} seeds")

    params = block.get("params", {})
    if not isinstance(params, dict):
        raise TypeError(f"{where}: params must be a table; got {_type_name(params)}")
    for key, value in params.items():
        if isinstance(value, list) and not value:
            raise ValueError(f"{where}: params.{key} is an empty list; give at least one value")
    method_params = block.get("method_params", {})
    if not isinstance(method_params, dict) or not all(
        isinstance(v, dict) for v in method_params.values()
    ):
        raise TypeError(f"{where}: method_params must be a table of tables (method -> params)")
    for m in method_params:
        if m not in methods:
            raise ValueError(
                f"{where}: method_params names method {m!r}, which is not in this grid's "
                f"methods ({', '.join(methods)})"
            )
    # Route every parameter now, so a typo fails before any run starts.
    for m in methods:
        for combo in _first_values(params):
            _route_params(METHODS[m], {**combo, **method_params.get(m, {})}, where)

    axes = [k for k, v in params.items() if isinstance(v, list)]
    if kind == "sensitivity" and len(axes) != 1:
        raise ValueError(
            f"{where}: a sensitivity grid needs exactly one params axis (a list value); "
            f"got {len(axes)}: {axes}"
        )
    method_seeds = block.get("method_seeds", {})
    if not isinstance(method_seeds, dict):
        raise TypeError(f"{where}: method_seeds must be a table (method -> list of seeds)")
    for m, s in method_seeds.items():
        if m not in methods:
            raise ValueError(
                f"{where}: method_seeds names method {m!r}, which is not in this grid's "
                f"methods ({', '.join(methods)})"
            )
        _check_seeds(s, f"{where} method_seeds.{m}")
    speed = _parse_speed(block.get("speed"), where)
    examples = block.get("examples", 5)
    if not _is_int(examples) or examples < 1:
        raise TypeError(f"{where}: examples must be an int >= 1; got {examples!r}")
    queries = block.get("queries")
    if queries is not None:
        if (
            not isinstance(queries, list)
            or not queries
            or not all(_is_int(q) and q >= 0 for q in queries)
        ):
            raise TypeError(f"{where}: queries must be a list of query positions (ints >= 0)")
        queries = tuple(queries)
    for key in ("examples", "queries"):
        if key in block and kind != "qualitative":
            raise ValueError(f"{where}: {key} applies to kind 'qualitative' only; kind is {kind!r}")
    warmup = block.get("warmup", True)
    if not isinstance(warmup, bool):
        raise TypeError(f"{where}: warmup must be true or false; got {warmup!r}")
    if "warmup" in block and kind != "timing":
        raise ValueError(f"{where}: warmup applies to kind 'timing' only; kind is {kind!r}")
    return GridBlock(
        name=name,
        kind=kind,
        title=title,
        description=description,
        datasets=tuple(ds_names),
        methods=tuple(methods),
        seeds=tuple(int(s) for s in seeds),
        params=dict(params),
        method_params={k: dict(v) for k, v in method_params.items()},
        method_seeds={k: tuple(int(x) for x in v) for k, v in method_seeds.items()},
        speed=speed,
        examples=int(examples),
        queries=queries,
        warmup=warmup,
    )


def _check_seeds(seeds, where: str) -> list[int]:
    if not isinstance(seeds, list) or not seeds or not all(_is_int(s) and s >= 0 for s in seeds):
        raise TypeError(f"{where}: must be a non-empty list of ints >= 0; got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"{where}: holds a value twice: {seeds!r}")
    return seeds


def _first_values(params: dict) -> list[dict]:
    """One combination per distinct key set; routing depends only on the keys."""
    return [{k: (v[0] if isinstance(v, list) else v) for k, v in params.items()}]


def _str_list(block: dict, key: str, where: str) -> list[str]:
    if key not in block:
        raise ValueError(f"{where}: missing required key {key!r}")
    value = block[key]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise TypeError(f"{where}: {key} must be a non-empty list of strings; got {value!r}")
    if len(set(value)) != len(value):
        raise ValueError(f"{where}: {key} holds a name twice: {value!r}")
    return value


def _parse_speed(speed, where: str):
    if speed is None:
        return None
    if _is_number(speed) and speed > 0:
        return float(speed)
    if (
        isinstance(speed, list)
        and len(speed) == 2
        and all(_is_number(v) for v in speed)
        and 0 < speed[0] <= speed[1]
    ):
        return (float(speed[0]), float(speed[1]))
    raise TypeError(
        f"{where}: speed must be a positive number or a [low, high] pair; got {speed!r}"
    )


def _defaults(cls) -> dict:
    """Constructor defaults of ``cls`` except ``random_state``, as JSON values."""
    import inspect

    out = {}
    for p in inspect.signature(cls.__init__).parameters.values():
        if p.name in ("self", "random_state") or p.default is inspect.Parameter.empty:
            continue
        if p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
            continue
        try:
            out[p.name] = json.loads(json.dumps(p.default, allow_nan=False))
        except (TypeError, ValueError):
            out[p.name] = repr(p.default)
    return out


def _full_params(spec, front: dict, filt: dict) -> tuple[dict, dict]:
    """Every constructor argument, defaults filled in, so a run's identity does not depend
    on whether a config spells out a default value."""
    from ..frontends import FRONTENDS
    from ..temporal import FILTERS

    front = {**_defaults(FRONTENDS[spec.frontend]), **front}
    filt = {**_defaults(FILTERS[spec.filter]), **filt} if spec.filter else dict(filt)
    return front, filt


def _route_params(spec, params: dict, where: str = "") -> tuple[dict, dict]:
    """Split ``params`` into front-end and filter constructor arguments of method ``spec``."""
    from ..frontends import FRONTENDS
    from ..temporal import FILTERS

    front_names = set(FRONTENDS[spec.frontend]._param_names())
    filt_names = set(FILTERS[spec.filter]._param_names()) if spec.filter else set()
    front, filt = {}, {}
    for key, value in params.items():
        if key.startswith("frontend."):
            bare, names, target = key[len("frontend.") :], front_names, front
        elif key.startswith("filter."):
            bare, names, target = key[len("filter.") :], filt_names, filt
        elif key in front_names:
            bare, names, target = key, front_names, front
        else:
            bare, names, target = key, filt_names, filt
        if bare == "random_state":
            raise ValueError(f"{where}: set random_state through 'seeds', not params")
        if bare not in names:
            raise ValueError(
                f"{where}: {key!r} is not a parameter of method {spec.name!r}; its front end "
                f"{spec.frontend!r} takes {sorted(front_names - {'random_state'})}"
                + (
                    f" and its filter {spec.filter!r} takes {sorted(filt_names - {'random_state'})}"
                    if spec.filter
                    else ""
                )
            )
        target[bare] = value
    return front, filt
