"""The report as data: a list of blocks, rendered to HTML and Markdown by Jinja2 templates.

The sections of the report (:mod:`flyvpr.experiments.sections`) add blocks
(headings, paragraphs, lists, tables, figures, code) to a :class:`Document`;
they never write markup.  ``templates/report.html.j2`` renders the blocks as
one self-contained HTML page (styles from ``templates/report.css`` inline,
figures embedded as base64 PNG, every text autoescaped) and
``templates/report.md.j2`` as Markdown with the figures as PNG files, so the
two outputs hold the same text and tables by construction.
"""

from __future__ import annotations

import base64
import functools
from dataclasses import dataclass, field

__all__ = ["Document"]


@dataclass
class Document:
    """Blocks of a report, in order, and the PNG bytes of its figures.

    Attributes
    ----------
    title : str
    blocks : list of dict
        Each has a ``type`` (``heading``, ``para``, ``items``, ``table``,
        ``figure`` or ``code``) and the fields the templates read.
    figures : dict of str to bytes
        Figure name -> PNG.
    """

    title: str
    blocks: list[dict] = field(default_factory=list)
    figures: dict[str, bytes] = field(default_factory=dict)

    def heading(self, level: int, text: str, anchor: str | None = None) -> None:
        """A heading of ``level`` 1-6; ``anchor`` is its id in HTML (a link target)."""
        self.blocks.append({"type": "heading", "level": level, "text": text, "anchor": anchor})

    def para(self, text: str, style: str | None = None) -> None:
        """A paragraph; ``style``: ``"protocol"``, ``"muted"`` or ``"error"`` (HTML class)."""
        self.blocks.append({"type": "para", "text": text, "style": style})

    def items(self, entries: list) -> None:
        """A bullet list; an entry is a str or a (text, anchor) pair (a link in HTML)."""
        pairs = [e if isinstance(e, tuple) else (e, None) for e in entries]
        self.blocks.append({"type": "items", "entries": pairs})

    def table(self, headers: list[str], rows: list[list], caption: str = "") -> None:
        """A table with one header row; cells are shown as ``str(cell)``."""
        rows = [[str(c) for c in row] for row in rows]
        self.blocks.append({"type": "table", "headers": headers, "rows": rows, "caption": caption})

    def figure(self, name: str, png: bytes, caption: str) -> None:
        """A figure; ``name`` is its file name (without ``.png``) next to the Markdown."""
        self.figures[name] = png
        self.blocks.append({"type": "figure", "name": name, "png": png, "caption": caption})

    def code(self, text: str) -> None:
        """Preformatted text (the config file)."""
        self.blocks.append({"type": "code", "text": text})

    def html(self) -> str:
        """The self-contained HTML page."""
        return _render("report.html.j2", title=self.title, blocks=self.blocks)

    def markdown(self, figure_dir: str) -> str:
        """Markdown; figures link to ``figure_dir/<name>.png``."""
        text = _render("report.md.j2", blocks=self.blocks, figure_dir=figure_dir)
        return text.rstrip("\n") + "\n"


def _markdown_cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


@functools.lru_cache(maxsize=1)
def _environment():
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("flyvpr.experiments", "templates"),
        # On for every template but Markdown's (which escapes only its table cells).
        autoescape=jinja2.select_autoescape(disabled_extensions=("md.j2",), default=True),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    env.filters["base64"] = lambda data: base64.b64encode(data).decode("ascii")
    env.filters["cell"] = _markdown_cell
    return env


def _render(template: str, **context) -> str:
    return _environment().get_template(template).render(**context)
