"""Write the API reference pages (``docs/api/*.rst``) from the package itself.

One page per public module or package of :data:`API_MODULES`.  A package's page documents the
names of its ``__all__`` at the path users import them from (``flyvpr.frontends.FlyHash``),
then each public submodule: its docstring, and the public names the package does not re-export.
Every object is documented once, so every cross-reference has one target.  A module listed in
:data:`API_MODULES` that does not exist (yet) is left out.  The pages are rebuilt on every
``sphinx-build`` (``docs/api/`` is not committed), so a new module or name shows up by itself.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import pkgutil
from pathlib import Path

#: the public modules, in the order of the reference's table of contents
API_MODULES = [
    "flyvpr",
    "flyvpr.methods",
    "flyvpr.frontends",
    "flyvpr.temporal",
    "flyvpr.metrics",
    "flyvpr.datasets",
    "flyvpr.images",
    "flyvpr.sources",
    "flyvpr.localization",
    "flyvpr.large",
    "flyvpr.view",
    "flyvpr.modelio",
    "flyvpr.evaluation",
    "flyvpr.experiments",
    "flyvpr.synthetic",
]

#: special methods documented where a class defines them with a docstring (a source is iterable)
SPECIAL_MEMBERS = "__call__, __iter__, __len__, __getitem__"

INTRO = """\
API reference
=============

Generated from the docstrings (numpydoc format).  Each object is documented where users
import it from: ``flyvpr.frontends.FlyHash``, not the file that defines it.  Shapes follow
the package's data contract: images are float32 ``(N, H, W)`` gray in [0, 1]; a score matrix
``S`` is ``(n_query, n_reference)`` with higher = more similar; ground truth is a boolean
matrix of ``S``'s shape.

.. toctree::
   :hidden:

"""


def _exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


def _public_names(module) -> list[str]:
    """``__all__``, or the public classes and functions the module defines."""
    names = getattr(module, "__all__", None)
    if names is not None:
        return [n for n in names if not n.startswith("__")]
    return [
        n
        for n, obj in vars(module).items()
        if not n.startswith("_")
        and (inspect.isclass(obj) or inspect.isfunction(obj))
        and obj.__module__ == module.__name__
    ]


def _submodules(package) -> list[str]:
    """Public submodules of ``package``, depth first, in name order."""
    if not hasattr(package, "__path__"):
        return []
    found = []
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        name = f"{package.__name__}.{info.name}"
        found.append(name)
        if info.ispkg:
            found += _submodules(importlib.import_module(name))
    return found


def _automodule(module, members: list[str], heading: str) -> str:
    """The module's docstring, then one autodoc directive per member."""
    name = module.__name__
    lines = [name, heading * len(name), "", f".. automodule:: {name}", "   :no-members:", ""]
    for member in members:
        obj = getattr(module, member)
        if inspect.isclass(obj) and not issubclass(obj, BaseException):
            # Encoders and filters show the calls they inherit (fit, score, filter, step, ...).
            lines += [
                f".. autoclass:: {name}.{member}",
                "   :members:",
                "   :inherited-members:",
                f"   :special-members: {SPECIAL_MEMBERS}",
            ]
        elif inspect.isclass(obj):
            lines += [f".. autoexception:: {name}.{member}"]
        elif callable(obj):
            lines += [f".. autofunction:: {name}.{member}"]
        else:
            lines += [f".. autodata:: {name}.{member}", "   :no-value:"]
        lines.append("")
    return "\n".join(lines)


def _reexports_page(package, documented: dict[int, str]) -> str:
    """The top-level page: where each name of ``flyvpr.__all__`` is documented.

    Names no other page documents (defined in a private module) are documented here.
    """
    names = _public_names(package)
    own = [n for n in names if id(getattr(package, n)) not in documented]
    lines = ["Names available as ``flyvpr.NAME``:", ""]
    for name in names:
        target = documented.get(id(getattr(package, name)), f"{package.__name__}.{name}")
        lines.append(f"* ``flyvpr.{name}``: :py:obj:`{target}`")
    return _automodule(package, own, "=") + "\n" + "\n".join(lines) + "\n"


def module_page(name: str, documented: dict[int, str]) -> str:
    """The page of one module or package; records what it documents in ``documented``."""
    module = importlib.import_module(name)
    parts = []
    for i, modname in enumerate([name, *_submodules(module)]):
        mod = importlib.import_module(modname)
        members = []
        for member in _public_names(mod):
            obj = getattr(mod, member, None)
            if obj is None or id(obj) in documented:
                continue
            documented[id(obj)] = f"{modname}.{member}"
            members.append(member)
        parts.append(_automodule(mod, members, "=" if i == 0 else "-"))
    return "\n".join(parts)


def write_api_pages(out: Path) -> list[str]:
    """Write ``out/index.rst`` and one page per module of :data:`API_MODULES`; return the names."""
    out.mkdir(parents=True, exist_ok=True)
    names = [n for n in API_MODULES if _exists(n)]
    documented: dict[int, str] = {}
    pages = {n: module_page(n, documented) for n in names if n != "flyvpr"}
    pages["flyvpr"] = _reexports_page(importlib.import_module("flyvpr"), documented)
    for name in names:
        _write_if_changed(out / f"{name}.rst", pages[name])
    index = INTRO + "".join(f"   {n}\n" for n in names) + "\n"
    for name in names:
        doc = (importlib.import_module(name).__doc__ or "").strip()
        index += f"* :mod:`{name}`: {doc.splitlines()[0] if doc else ''}\n"
    _write_if_changed(out / "index.rst", index)
    return names


def _write_if_changed(path: Path, text: str) -> None:
    # An unchanged page keeps its time stamp, so Sphinx does not re-read it.
    if not path.exists() or path.read_text() != text:
        path.write_text(text)
