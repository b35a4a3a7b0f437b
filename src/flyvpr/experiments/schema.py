"""A small declarative schema for TOML tables: dataclass fields that say what they accept.

A config block is a frozen dataclass whose fields are declared with :func:`key`:
the kind of value (an instance of one of the :class:`Value` classes below),
a default or none (required), one line of documentation and, optionally, the
values of another key the field is restricted to (``only_if``).
:func:`check_table` is the one checker: it reads a TOML table against such a
class and returns the converted values, and :func:`markdown_table` writes the
same declarations as the reference table of the documentation, so the
documentation cannot drift from what is checked.

Every error names where the table is (file and block), the key path, what was
expected and what arrived: ``TypeError`` when the value has the wrong type,
``ValueError`` when its type is right but its value is not.

Why not a validation library (pydantic, cattrs, voluptuous): the messages must
name TOML blocks and key paths (``paper.toml [[grids]] #2 ('eval'): seeds``)
rather than Python classes and models, the reference page must be generated
from the same declarations, some choices come from flyvpr's registries at run
time, and TOML values must reach the run identity unconverted (an ``int``
stays an ``int``); plain dataclasses and this one checker do all of that
without a new dependency.
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "Invalid",
    "Value",
    "Text",
    "Flag",
    "Int",
    "Number",
    "Choice",
    "ListOf",
    "Either",
    "TableOf",
    "Axis",
    "PathText",
    "Block",
    "Blocks",
    "Context",
    "key",
    "build",
    "check_table",
    "schema_fields",
    "markdown_table",
]

#: metadata key of a schema field
_SPEC = "flyvpr.schema"


class Invalid(Exception):
    """A value does not match its :class:`Value` (turned into TypeError/ValueError)."""

    def __init__(self, value, *, wrong_type: bool, reason: str = ""):
        super().__init__(reason)
        self.value = value
        self.wrong_type = wrong_type
        self.reason = reason
        self.subkey = ""  # ".name" inside a table of values
        self.expected: str | None = None  # what the innermost table expected there


@dataclass
class Context:
    """What a check may need besides the value: the config folder and known names."""

    base_dir: Path = Path(".")
    source: str = "<config>"
    names: dict[str, tuple[str, ...]] = field(default_factory=dict)


def toml_type(value) -> str:
    """The TOML name of a parsed value's type (for messages)."""
    for types, name in (
        (bool, "boolean"),
        (int, "integer"),
        (float, "float"),
        (str, "string"),
        (list, "array"),
        (dict, "table"),
    ):
        if isinstance(value, types):
            return name
    return type(value).__name__


def show(value, limit: int = 80) -> str:
    """A value as TOML-like text, cut to ``limit`` characters."""
    try:
        text = json.dumps(value, ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# -- kinds of value ------------------------------------------------------------------------------
class Value:
    """One kind of value; ``expected`` phrases it for messages and documentation."""

    @property
    def expected(self) -> str:
        return "a value"

    def check(self, value, ctx: Context):
        """Return ``value`` converted, or raise :class:`Invalid`."""
        return value


@dataclass(frozen=True)
class Text(Value):
    """A string, optionally matching ``pattern`` (described by ``expected``)."""

    expected: str = "a string"
    pattern: str | None = None

    def check(self, value, ctx):
        if not isinstance(value, str):
            raise Invalid(value, wrong_type=True)
        if self.pattern is not None and not re.fullmatch(self.pattern, value):
            raise Invalid(value, wrong_type=False)
        return value


@dataclass(frozen=True)
class PathText(Value):
    """A file system path; ``resolve``: return it absolute (relative to the config folder)."""

    resolve: bool = False
    expected: str = "a path (relative paths start at the config file's folder)"

    def check(self, value, ctx):
        if not isinstance(value, str):
            raise Invalid(value, wrong_type=True)
        return resolve_path(value, ctx.base_dir) if self.resolve else value


def resolve_path(path: str, base_dir: Path) -> str:
    """``path`` made absolute against ``base_dir`` (``~`` expanded)."""
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else (Path(base_dir) / p).resolve())


@dataclass(frozen=True)
class Flag(Value):
    expected: str = "true or false"

    def check(self, value, ctx):
        if not isinstance(value, bool):
            raise Invalid(value, wrong_type=True)
        return value


@dataclass(frozen=True)
class Int(Value):
    """An integer (not a boolean) at least ``minimum``."""

    minimum: int = 0

    @property
    def expected(self) -> str:
        return f"an integer >= {self.minimum}"

    def check(self, value, ctx):
        if isinstance(value, bool) or not isinstance(value, int):
            raise Invalid(value, wrong_type=True)
        if value < self.minimum:
            raise Invalid(value, wrong_type=False)
        return value


@dataclass(frozen=True)
class Number(Value):
    """A finite integer or float (not a boolean), above ``minimum`` (or at it, if not strict).

    The value is kept as written (an int stays an int) unless ``as_float``.
    """

    minimum: float = 0.0
    strict: bool = True
    as_float: bool = False

    @property
    def expected(self) -> str:
        return f"a number {'>' if self.strict else '>='} {self.minimum:g}"

    def check(self, value, ctx):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise Invalid(value, wrong_type=True)
        above = value > self.minimum if self.strict else value >= self.minimum
        if not above or value == float("inf"):  # NaN is not `above`
            raise Invalid(value, wrong_type=False)
        return float(value) if self.as_float else value


@dataclass(frozen=True)
class Choice(Value):
    """A name from a list known at check time: ``names(ctx)`` (a registry, the blocks)."""

    what: str
    names: Callable[[Context], Iterable[str]]
    listed: bool = True  # list the names in `expected` (a short, fixed list)

    @property
    def expected(self) -> str:
        if self.listed:
            return "one of " + ", ".join(map(repr, self.names(Context())))
        return f"a {self.what} name"

    def check(self, value, ctx):
        if not isinstance(value, str):
            raise Invalid(value, wrong_type=True)
        known = list(self.names(ctx))
        if value not in known:
            reason = "" if self.listed else f"known {self.what}s: {', '.join(known)}"
            raise Invalid(value, wrong_type=False, reason=reason)
        return value


@dataclass(frozen=True)
class ListOf(Value):
    """A non-empty array of ``item`` (``items`` names them in the plural); a tuple."""

    item: Value
    items: str
    length: int | None = None
    distinct: bool = False
    ordered: bool = False  # low <= high (for a [low, high] pair)

    @property
    def expected(self) -> str:
        if self.length is not None:
            text = f"a list of {self.length} {self.items}"
        else:
            text = f"a non-empty list of {'distinct ' if self.distinct else ''}{self.items}"
        return text + (", the first <= the second" if self.ordered else "")

    def check(self, value, ctx):
        if not isinstance(value, list):
            raise Invalid(value, wrong_type=True)
        if not value or (self.length is not None and len(value) != self.length):
            raise Invalid(value, wrong_type=False)
        out = []
        for i, item in enumerate(value):
            try:
                out.append(self.item.check(item, ctx))
            except Invalid as exc:
                reason = f"item {i + 1}, {show(item)}, is not {self.item.expected}"
                reason += f"; {exc.reason}" if exc.reason else ""
                raise Invalid(value, wrong_type=exc.wrong_type, reason=reason) from None
        if self.distinct:
            twice = [show(v) for i, v in enumerate(value) if v in value[:i]]
            if twice:
                raise Invalid(value, wrong_type=False, reason=f"it holds {', '.join(twice)} twice")
        if self.ordered and any(a > b for a, b in zip(out, out[1:], strict=False)):
            raise Invalid(value, wrong_type=False)
        return tuple(out)


@dataclass(frozen=True)
class Either(Value):
    """The first of ``options`` that accepts the value."""

    options: tuple[Value, ...]

    @property
    def expected(self) -> str:
        return " or ".join(o.expected for o in self.options)

    def check(self, value, ctx):
        wrong_type = True
        for option in self.options:
            try:
                return option.check(value, ctx)
            except Invalid as exc:
                wrong_type = wrong_type and exc.wrong_type
        raise Invalid(value, wrong_type=wrong_type)


@dataclass(frozen=True)
class TableOf(Value):
    """A table of ``NAME = value``; converted to a dict."""

    value: Value
    keys: str = "NAME"

    @property
    def expected(self) -> str:
        return f"a table of {self.keys} = {self.value.expected}"

    def check(self, value, ctx):
        if not isinstance(value, dict):
            raise Invalid(value, wrong_type=True)
        out = {}
        for name, item in value.items():
            try:
                out[name] = self.value.check(item, ctx)
            except Invalid as exc:
                exc.subkey = f".{name}{exc.subkey}"
                if exc.expected is None:
                    exc.expected = self.value.expected
                raise
        return out


@dataclass(frozen=True)
class Axis(Value):
    """A grid parameter: one value, or a non-empty array (an axis of the grid)."""

    expected: str = "a value, or a non-empty list of values (an axis of the grid)"

    def check(self, value, ctx):
        if isinstance(value, list) and not value:
            raise Invalid(value, wrong_type=False, reason="an empty list gives no runs")
        return value


@dataclass(frozen=True)
class Block(Value):
    """A ``[header]`` table read into ``cls`` (see :func:`build`)."""

    cls: type
    header: str

    @property
    def expected(self) -> str:
        return f"a [{self.header}] table"

    def check(self, value, ctx):
        if not isinstance(value, dict):
            raise Invalid(value, wrong_type=True)
        return build(self.cls, value, f"{ctx.source} [{self.header}]", ctx)


@dataclass(frozen=True)
class Blocks(Value):
    """One or more ``[[header]]`` tables read into ``cls``, with distinct names.

    Their names become known to the keys checked after them, in
    ``ctx.names[header]`` (a grid names the datasets declared before it).
    """

    cls: type
    header: str
    by_name: bool = False  # a dict name -> block instead of a list

    @property
    def expected(self) -> str:
        return f"one or more [[{self.header}]] blocks"

    def check(self, value, ctx):
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise Invalid(value, wrong_type=True)
        if not value:
            raise Invalid(value, wrong_type=False)
        blocks: list[Any] = []
        for i, table in enumerate(value):
            block = build(self.cls, table, f"{ctx.source} [[{self.header}]] #{i + 1}", ctx)
            if any(b.name == block.name for b in blocks):
                raise ValueError(
                    f"{ctx.source}: [[{self.header}]] name {block.name!r} is used by two blocks"
                )
            blocks.append(block)
        ctx.names[self.header] = tuple(b.name for b in blocks)
        return {b.name: b for b in blocks} if self.by_name else blocks


def build(cls, table, where: str, ctx: Context):
    """``cls.from_table(table, where, ctx)`` if defined, else ``cls(**checked values)``."""
    if hasattr(cls, "from_table"):
        return cls.from_table(table, where, ctx)
    values, _ = check_table(cls, table, where, ctx)
    return cls(**values)


# -- fields and the checker ----------------------------------------------------------------------
_REQUIRED = object()


@dataclass(frozen=True)
class FieldSpec:
    """What :func:`key` records on a dataclass field."""

    value: Value
    doc: str
    required: bool
    default_doc: str  # "" when required
    literal: bool  # default_doc is the default value in TOML, not words
    only_if: tuple[str, tuple[str, ...]] | None


def key(
    value: Value,
    doc: str,
    *,
    default=_REQUIRED,
    default_doc: str | None = None,
    only_if: tuple[str, tuple[str, ...]] | None = None,
):
    """Declare a dataclass field as a key of a TOML table.

    Parameters
    ----------
    value : Value
        What the key accepts.
    doc : str
        One line for the documentation.
    default : optional
        Value when the key is absent; without it the key is required.
    default_doc : str, optional
        How the documentation states the default (when it is not a literal).
    only_if : (str, tuple of str), optional
        ``(other_key, allowed)``: the key may only be given when ``other_key``
        holds one of ``allowed``.
    """
    required = default is _REQUIRED
    literal = default_doc is None and not required
    if default_doc is None:
        default_doc = "" if required else show(default)
    spec = FieldSpec(value, doc, required, default_doc, literal, only_if)
    if required:
        return field(metadata={_SPEC: spec}, kw_only=True)
    if isinstance(default, (list, dict)):
        factory = type(default)
        return field(default_factory=lambda: factory(default), metadata={_SPEC: spec}, kw_only=True)
    return field(default=default, metadata={_SPEC: spec}, kw_only=True)


def schema_fields(cls) -> list[tuple[str, FieldSpec]]:
    """(key, spec) of every field of ``cls`` declared with :func:`key`, in order."""
    return [(f.name, f.metadata[_SPEC]) for f in dataclasses.fields(cls) if _SPEC in f.metadata]


def fail(where: str, path: str, spec_value: Value, exc: Invalid):
    """Raise the TypeError/ValueError for ``exc`` at ``where``/``path``."""
    got = show(exc.value)
    if exc.wrong_type:
        got += f" ({toml_type(exc.value)})"
    expected = exc.expected or spec_value.expected
    message = f"{where}: {path}{exc.subkey} must be {expected}; got {got}"
    if exc.reason:
        message += f": {exc.reason}"
    raise (TypeError if exc.wrong_type else ValueError)(message) from None


def check_table(cls, table, where: str, ctx: Context) -> tuple[dict[str, Any], str]:
    """Check a TOML table against the :func:`key` fields of ``cls``.

    Parameters
    ----------
    cls : dataclass type
    table : object
        The parsed TOML value (must be a table).
    where : str
        Where the table is, e.g. ``"paper.toml [[grids]] #2"``; a ``name`` key,
        when the schema has one, is appended once checked.
    ctx : Context

    Returns
    -------
    values : dict
        Field name -> converted value, for every key the table gives.
    where : str
        ``where`` with the table's name, for later messages.

    Raises
    ------
    TypeError, ValueError
        For a table of another type, an unknown or missing key, a value of the
        wrong type or value, or a key given where ``only_if`` forbids it.
    """
    if not isinstance(table, dict):
        raise TypeError(f"{where}: expected a table; got {show(table)} ({toml_type(table)})")
    fields = dict(schema_fields(cls))
    values: dict[str, Any] = {}

    def check(name: str) -> None:
        spec = fields[name]
        if name not in table:
            if spec.required:
                raise ValueError(f"{where}: missing required key {name!r}: {spec.value.expected}")
            return
        try:
            values[name] = spec.value.check(table[name], ctx)
        except Invalid as exc:
            fail(where, name, spec.value, exc)

    if "name" in fields:  # first: the name joins `where`
        check("name")
        where = f"{where} ({values['name']!r})"
    unknown = [k for k in table if k not in fields]
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(fields)}"
        )
    for name in fields:
        if name != "name":
            check(name)
    for name, spec in fields.items():
        if spec.only_if and name in table:
            other, allowed = spec.only_if
            if values.get(other) not in allowed:
                raise ValueError(
                    f"{where}: {name} applies to {other} {' or '.join(map(repr, allowed))} only; "
                    f"{other} is {values.get(other)!r}"
                )
    return values, where


def markdown_table(cls, extra: Callable[[str], str] | None = None) -> str:
    """The :func:`key` fields of ``cls`` as a Markdown table (key, value, default, meaning).

    ``extra(key)`` may add text to a key's meaning (e.g. which loaders take it).
    """
    lines = ["| key | value | default | meaning |", "|---|---|---|---|"]
    for name, spec in schema_fields(cls):
        value = spec.value.expected
        if isinstance(spec.value, Choice) and spec.value.listed:
            value = "one of " + ", ".join(f"`{n}`" for n in spec.value.names(Context()))
        meaning = spec.doc
        if spec.only_if:
            other, allowed = spec.only_if
            meaning += f" Only with {other} " + " or ".join(f"`{a}`" for a in allowed) + "."
        if extra is not None:
            meaning += extra(name)
        default = f"`{spec.default_doc}`" if spec.literal else spec.default_doc or "required"
        cells = [f"`{name}`", value, default, meaning]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines)
