"""The ``flyvpr`` parser as the command-line reference page shows it.

sphinx-argparse reads descriptions and help texts as reStructuredText, where ``Recall@1``
looks like an e-mail address and becomes a ``mailto:`` link; this escapes the ``@``.  The
parser is otherwise the program's own (:func:`flyvpr.cli.build_parser`).
"""

from __future__ import annotations

import argparse
import re

from flyvpr.cli import build_parser

_AT = re.compile(r"(?<=\w)@(?=\w)")


def _escape(text):
    return _AT.sub(r"\\@", text) if isinstance(text, str) else text


def _walk(parser: argparse.ArgumentParser) -> None:
    parser.description = _escape(parser.description)
    parser.epilog = _escape(parser.epilog)
    for action in parser._actions:
        action.help = _escape(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = _escape(choice.help)
            for sub in dict.fromkeys(action.choices.values()):
                _walk(sub)


def parser() -> argparse.ArgumentParser:
    """:func:`flyvpr.cli.build_parser` with its texts escaped for reStructuredText."""
    p = build_parser()
    _walk(p)
    return p
