"""``flyvpr datasets`` and ``flyvpr methods``: what flyvpr can read and run."""

from __future__ import annotations

import importlib.util
import shutil
import textwrap

from ..datasets import DATASETS
from ..frontends import FRONTENDS
from ..images import FOLDER_RULES
from ..methods import ALIASES, METHODS, method_names
from ..temporal import FILTERS


def cmd_datasets(args) -> int:
    for name, spec in DATASETS.items():
        print(f"{name}: {spec.description}")
        print(textwrap.indent(spec.layout.strip(), "    "))
        print(f"    options: {', '.join('--' + o.replace('_', '-') for o in spec.options)}")
        print()
    width = max(60, min(100, shutil.get_terminal_size((100, 24)).columns))
    for line in FOLDER_RULES.splitlines():
        print(textwrap.fill(line, width, subsequent_indent="  "))
    return 0


def _summary(cls) -> str:
    return (cls.__doc__ or cls.__name__).strip().splitlines()[0]


def _needs(cls) -> str:
    """The pip extra a part needs, marked when its modules cannot be imported here."""
    modules = getattr(cls, "requires", ())
    if not modules:
        return ""
    available = all(importlib.util.find_spec(m) is not None for m in modules)
    return f"[{getattr(cls, 'extra', 'torch')}]" + ("" if available else " not installed")


def _print_parts(title: str, registry: dict, width: int) -> None:
    """One entry per part: name and needed extra, then its summary wrapped to ``width``."""
    print(title)
    name_width = max(len(n) for n in registry) + 2
    for name, cls in registry.items():
        needs = _needs(cls)
        head = f"  {name.ljust(name_width)}"
        lines = textwrap.wrap(
            _summary(cls) + (f" {needs}" if needs else ""),
            width=max(30, width - len(head)),
        )
        print(head + lines[0])
        for line in lines[1:]:
            print(" " * len(head) + line)


def cmd_methods(args) -> int:
    if args.all:
        available = set(method_names(available_only=True))
        for name in METHODS:
            print(
                name if name in available else f"{name}  (needs {', '.join(METHODS[name].extras)})"
            )
        return 0
    width = min(100, shutil.get_terminal_size((100, 24)).columns)
    _print_parts("front ends (single frames):", FRONTENDS, width)
    print()
    _print_parts("temporal filters (sequences):", FILTERS, width)
    print()
    aliases = ", ".join(f"{a} = {t}" for a, t in ALIASES.items())
    print(
        textwrap.fill(
            f"A method is a front end alone (e.g. flynet) or FRONT+FILTER (e.g. flynet+cann): "
            f"{len(METHODS)} names in all (`flyvpr methods --all` lists them). Aliases: {aliases}.",
            width=width,
        )
    )
    return 0


def register(sub) -> None:
    """Add ``datasets`` and ``methods`` to the subcommand parsers ``sub``."""
    p = sub.add_parser("datasets", help="list dataset layouts and their options")
    p.set_defaults(func=cmd_datasets)
    p = sub.add_parser(
        "methods",
        help="list the front ends and filters that make up the methods, and the extras they need",
    )
    p.add_argument(
        "--all", action="store_true", help="list every method name, one per line (for scripts)"
    )
    p.set_defaults(func=cmd_methods)
