"""A small local Sphinx extension: two docstring fixes and short cross-references.

* A fitted attribute inside a type (``shape (n_hidden, n_samples_)``) is a hyperlink reference
  to reStructuredText (a word ending in ``_``): the underscore is escaped.
* A section titled "Attributes set by ``fit``" becomes numpydoc's "Attributes" section.
* ``:class:`Method``` written in a module that imports ``Method``, or ``:meth:`step``` in a
  module docstring, names an object documented elsewhere: the reference is resolved to it when
  exactly one documented object fits (see :func:`resolve_short_reference`).
"""

from __future__ import annotations

import inspect
import pkgutil
import re
import warnings

from sphinx.util.nodes import make_refnode

_TYPE_LINE = re.compile(r"^(\s*[\w*, ]+ : )(.*)$")
_TRAILING_UNDERSCORE = re.compile(r"(?<=\w)_(?=\W|$)")
_FIT_ATTRIBUTES = "Attributes set by"

# numpydoc also parses the raw docstring for the signature, and warns about the section there.
warnings.filterwarnings("ignore", message="Unknown section Attributes Set By", category=UserWarning)


def fix_docstring(app, what, name, obj, options, lines):
    """Edit ``lines`` in place before numpydoc reads them."""
    for i, line in enumerate(lines):
        m = _TYPE_LINE.match(line)
        if m and "`" not in m.group(2):
            lines[i] = m.group(1) + _TRAILING_UNDERSCORE.sub(r"\\_", m.group(2))
        if line.strip().startswith(_FIT_ATTRIBUTES) and i + 1 < len(lines):
            indent = line[: len(line) - len(line.lstrip())]
            lines[i], lines[i + 1] = indent + "Attributes", indent + "-" * len("Attributes")


def _resolve(path: str):
    try:
        return pkgutil.resolve_name(path)
    except (ImportError, AttributeError, ValueError):
        return None


def _owner_and_object(documented_name: str):
    owner_path, _, attr = documented_name.rpartition(".")
    owner = _resolve(owner_path)
    return (owner if inspect.isclass(owner) else None), attr


def _defined_in(documented_name: str, module: str | None) -> bool:
    """Whether the object (or, for a method, its class) is defined in ``module``."""
    owner, _ = _owner_and_object(documented_name)
    obj = owner if owner is not None else _resolve(documented_name)
    return getattr(obj, "__module__", None) == module


def _defines(documented_name: str) -> bool:
    """Whether a method's class defines it itself (rather than inheriting it)."""
    owner, attr = _owner_and_object(documented_name)
    return owner is None or attr in vars(owner)


def resolve_short_reference(app, env, node, contnode):
    """Resolve a Python reference Sphinx could not, when exactly one documented object fits.

    The candidates are the documented objects with the target's last name.  If the target
    imports (as written, or relative to the current module or class), only the candidates
    that are that same object stay.  Then the candidates in the current class, else those
    defined in the current module, else those documented inside the current package, then the
    class that defines a method rather than inherits it, are preferred.  Anything else stays
    unresolved, and ``-n -W`` fails the build.
    """
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"].lstrip("~.")
    module, cls = node.get("py:module"), node.get("py:class")
    domain = env.get_domain("py")
    last = target.rpartition(".")[2]
    # Canonical aliases (the defining module's path of an object documented elsewhere) are
    # the same object under a second name: the documented name is the one to link.
    same_name = [
        n for n, e in domain.objects.items() if n.rpartition(".")[2] == last and not e.aliased
    ]
    found = same_name
    scopes = [target] + [f"{s}.{target}" for s in (f"{module}.{cls}", module) if s]
    wanted = next((obj for obj in map(_resolve, scopes) if obj is not None), None)
    if wanted is not None:
        found = [n for n in found if _resolve(n) is wanted] or found
    for keep in (
        lambda n: n.endswith(f".{target}"),
        lambda n: bool(cls) and n.endswith(f".{cls}.{last}"),
        lambda n: _defined_in(n, module),
        lambda n: bool(module) and n.startswith(f"{module}."),
        _defines,
    ):
        if len(found) > 1:
            found = [n for n in found if keep(n)] or found
    if len(found) > 1 and len({id(_resolve(n)) for n in found}) == 1:
        # One inherited method seen through many classes: link the class that defines it.
        obj = _resolve(found[0])
        found = [n for n in same_name if _defines(n) and _resolve(n) is obj] or found
    if len(found) != 1:
        return None
    entry = domain.objects[found[0]]
    return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode)


def setup(app):
    # Before numpydoc (priority 500) reads the docstring.
    app.connect("autodoc-process-docstring", fix_docstring, priority=400)
    app.connect("missing-reference", resolve_short_reference)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
