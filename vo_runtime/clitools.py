"""What both command lines (`toolkit` and `python -m vo_runtime`) share: bad input is one `error:` line.

- `OneLineArgumentParser` keeps argparse's usage text for ``--help`` but reports a bad option as one line.
- `run_guarded` parses, runs, and turns every failure into one ``error:`` line on stderr: exit 2 for bad
  input (the given error types, unreadable/unwritable files, out of memory), 130 for Ctrl-C, and 1 for an
  unexpected failure (a bug: ``EDGEFEAT_TRACEBACK=1`` shows its traceback). Python warnings from libraries
  are held back: a failed command shows only its error line, a finished one each warning once, one line.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from typing import Callable, NoReturn, Sequence

from vo_runtime.errors import MESSAGE_LIMIT, first_line

BAD_INPUT, INTERNAL_ERROR, INTERRUPTED = 2, 1, 130
TRACEBACK_VARIABLE = "EDGEFEAT_TRACEBACK"


class OneLineArgumentParser(argparse.ArgumentParser):
    """argparse with one-line errors; sub-parsers inherit the class (argparse uses ``type(self)``)."""

    def error(self, message: str) -> NoReturn:
        self.exit(BAD_INPUT, f"error: {self.prog}: {' '.join(message.split())} (see {self.prog} --help)\n")


def command_parser(prog: str, description: str, epilog: str,
                   add_arguments: Callable[[argparse.ArgumentParser], None],
                   run: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    """The parser of one runtime command (``python -m vo_runtime``, ``... verify``): one-line errors, the epilog
    as written with ``{prog}`` filled in, ``func`` set to ``run``."""
    parser = OneLineArgumentParser(prog=prog, description=description, epilog=epilog.format(prog=prog),
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def silence_native_logs() -> None:
    """OpenCV logs its own '[ERROR:...]' line for a corrupt image before we report it: keep stderr to ours."""
    try:
        import cv2

        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except (ImportError, AttributeError):  # an OpenCV without the logging module prints nothing to silence
        pass


OUT_OF_MEMORY = "out of memory: use a smaller input size, batch or image count"
# How torch and onnxruntime say an allocation failed: a RuntimeError, not a MemoryError (torch's CPU allocator:
# "can't allocate memory: you tried to allocate 4000000000000 bytes"; CUDA: "CUDA out of memory").
ALLOCATION_FAILURES = ("can't allocate memory", "out of memory", "failed to allocate memory", "bad_alloc")


def is_allocation_failure(exc: BaseException) -> bool:
    return isinstance(exc, RuntimeError) and any(text in str(exc).lower() for text in ALLOCATION_FAILURES)


def _report_warnings(caught: list[warnings.WarningMessage]) -> None:
    """Library warnings of a command that succeeded, one line each and once (no source line); a command that
    fails reports only its error line."""
    for text in dict.fromkeys(f"{w.category.__name__}: {' '.join(str(w.message).split())}" for w in caught):
        print(f"warning: {text[:MESSAGE_LIMIT]}", file=sys.stderr)


def _report(message: str) -> None:
    print(f"error: {' '.join(message.split())}", file=sys.stderr)


def run_guarded(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
                user_errors: tuple[type[BaseException], ...]) -> int:
    """Parse ``argv`` and run ``args.func(args)``; return the exit code, never raise (see the module doc)."""
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option, already reported in one line (2)
        return exc.code if isinstance(exc.code, int) else BAD_INPUT
    silence_native_logs()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            code = int(args.func(args) or 0)
        _report_warnings(caught)
        return code
    except user_errors as exc:  # our own messages: one line already, never shortened
        _report(first_line(exc, limit=None))
    except MemoryError:
        _report(OUT_OF_MEMORY)
    except OSError as exc:  # a file we could not read or write (full disk, permissions)
        where = f": {exc.filename}" if exc.filename else ""
        _report(f"{exc.strerror or first_line(exc)}{where}")
    except KeyboardInterrupt:
        _report("interrupted")
        return INTERRUPTED
    except Exception as exc:  # noqa: BLE001 - the last resort: a bug, still one line unless asked for more
        if is_allocation_failure(exc):
            _report(OUT_OF_MEMORY)
            return BAD_INPUT
        if os.environ.get(TRACEBACK_VARIABLE):
            raise
        _report(f"internal error ({type(exc).__name__}: {first_line(exc)}); rerun with {TRACEBACK_VARIABLE}=1 "
                "for the traceback and report it")
        return INTERNAL_ERROR
    return BAD_INPUT
