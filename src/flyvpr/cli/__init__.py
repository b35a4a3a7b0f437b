"""Command-line interface: ``flyvpr <command> ...``.

``main(argv) -> int`` returns 0 on success, 1 after a runtime error (one line on
stderr) and 2 for a usage error.  Each subcommand lives in its own module beside
its options (``evaluate``/``fit``, ``localize``, ``demo``, ``experiment``/``report``,
``datasets``/``methods``); :func:`build_parser` collects them.  Nothing else in
the package imports this package.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from contextlib import contextmanager

from .._version import __version__
from . import demo, evaluate, experiment, info, localize, map
from ._common import UsageError, as_options

__all__ = ["main", "build_parser"]

logger = logging.getLogger("flyvpr")

#: subcommand modules in the order ``flyvpr --help`` lists them
COMMAND_MODULES = (evaluate, map, localize, info, demo, experiment)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr (exit code 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: usage error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``flyvpr`` argument parser with every subcommand."""
    parser = _Parser(
        prog="flyvpr",
        description=(
            "Visual place recognition for robots: a route is mapped once; every later frame "
            "(a recording, a camera or a stream) is matched to a place of the map, with a "
            "confidence and whether it is localized. The default method is kenyon+cann (a "
            "fly-inspired front end and a CANN over places and speeds); the paper's "
            "FlyNet+CANN, SeqSLAM and the other baselines are there too, scored with "
            "precision-recall AUC and Recall@K."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Run `flyvpr COMMAND --help` for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"flyvpr {__version__}")
    parser.add_argument("--verbose", "-v", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


class Terminated(BaseException):
    """SIGTERM arrived: unwinds like Ctrl-C, so every temporary file is removed on the way out."""


def _raise_terminated(signum, frame):
    raise Terminated


@contextmanager
def _sigterm_unwinds():
    """While the CLI runs, SIGTERM raises :class:`Terminated` instead of killing the process.

    Only the main thread can install handlers; elsewhere (a test runner's worker thread) the
    default stays.  The previous handler is restored on the way out.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _sizing_options(args) -> str:
    """The options that set how much a run allocates, as given (for an out-of-memory line)."""
    parts = [f"--param {k}={v!r}" for k, v in getattr(args, "param", None) or []]
    for name in ("size", "count", "places", "first"):
        value = getattr(args, name, None)
        if value is not None:
            shown = f"{value[0]}x{value[1]}" if name == "size" else value
            parts.append(f"--{name} {shown}")
    return ", ".join(parts) or "none"


def _interrupt_in(exc: BaseException) -> BaseException | None:
    """The KeyboardInterrupt or :class:`Terminated` chained to ``exc`` (as cause or context),
    if any."""
    seen: set[int] = set()
    node: BaseException | None = exc
    while node is not None and id(node) not in seen:
        seen.add(id(node))
        if isinstance(node, (KeyboardInterrupt, Terminated)):
            return node
        node = node.__cause__ or node.__context__
    return None


def _terminated(args) -> str:
    """The line for a run ended by SIGTERM: a run that writes its records as it goes (live,
    or ``--realtime``) sets ``args.records_kept`` to the file that keeps them."""
    kept = getattr(args, "records_kept", None)
    if kept is not None and os.path.lexists(kept):  # (none: no record was made)
        return f"flyvpr: terminated by SIGTERM; the records written until then are kept in {kept}"
    return "flyvpr: terminated by SIGTERM; no half-written file left"


def main(argv=None) -> int:
    """Run the CLI; returns the process exit code.

    0 on success; 1 after a runtime error (one line on stderr naming the file, option or
    parameter); 2 for a usage error (one line naming the option); 130 after Ctrl-C and 143
    after SIGTERM, with no output file written or half-written.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help/--version (0) or usage error (2)
        return int(exc.code or 0)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        with _sigterm_unwinds():
            code = int(args.func(args))
            sys.stdout.flush()  # a closed pipe shows here, inside the handlers below
        return code
    except Terminated:
        print(_terminated(args), file=sys.stderr)
        return 143
    except BrokenPipeError:
        # `flyvpr methods | head`: the reader left; stop quietly, as `ls | head` does.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except UsageError as exc:
        print(f"flyvpr {args.command}: usage error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flyvpr: interrupted", file=sys.stderr)
        return 130
    except SystemError as exc:
        # Ctrl-C or SIGTERM inside a compiled (numba) kernel comes out as "returned a result
        # with an exception set", the interrupt chained to it
        cause = _interrupt_in(exc)
        if isinstance(cause, Terminated):
            print(_terminated(args), file=sys.stderr)
            return 143
        if isinstance(cause, KeyboardInterrupt):
            print("flyvpr: interrupted", file=sys.stderr)
            return 130
        raise
    except MemoryError:
        print(
            f"flyvpr {args.command}: error: out of memory: the run asked for more memory than "
            f"this machine has available; options given: {_sizing_options(args)}",
            file=sys.stderr,
        )
        return 1
    except (ValueError, TypeError, OSError, ImportError, RuntimeError) as exc:
        message = as_options(" ".join(str(exc).split())) or type(exc).__name__
        print(f"flyvpr {args.command}: error: {message}", file=sys.stderr)
        logger.debug("traceback", exc_info=True)
        return 1
