"""`toolkit` entry point: one subcommand per module, each registering its own parser.

A subcommand module (``toolkit/cmd_<name>.py``) exposes ``register(subparsers)`` which adds a parser
whose ``func(args) -> int`` does the work. Adding a command is one line in ``COMMAND_MODULES``.
Every failure a user can cause is one ``error:`` line on stderr and exit code 2 (`run_guarded`).
"""
from __future__ import annotations

import argparse
import importlib
import sys

from toolkit import __version__
from toolkit.errors import ToolkitError
from vo_runtime.clitools import OneLineArgumentParser, run_guarded
from vo_runtime.errors import VORuntimeError


def user_errors() -> tuple[type[Exception], ...]:
    """Each layer's own bad-input errors, printed as one `error:` line with exit 2 (the layers never import
    toolkit). Imported only once the toolkit extra is known to be there: `models` imports torch."""
    from export.errors import ExportError
    from models.errors import ModelError
    from profiles.errors import ProfileError

    return ToolkitError, VORuntimeError, ProfileError, ModelError, ExportError


# Order is the order shown by `toolkit --help`.
COMMAND_MODULES: list[str] = [
    "toolkit.cmd_export",
    "toolkit.cmd_eval",
    "toolkit.cmd_label",
    "toolkit.cmd_train",
    "toolkit.cmd_prune",
    "toolkit.cmd_quantise",
    "toolkit.cmd_profile",
    "toolkit.cmd_vo",
    "toolkit.cmd_verify",
]


EPILOG = """\
Run `toolkit <command> --help` for the options and examples of each command.

environment:
  EDGEFEAT_DATA           data folder with train_images/, hpatches_v_dogman/, lowlight_pairs/ (default: ../shared/data
                          from the working directory or beside the source tree); prune's default images and metrics
  EDGEFEAT_ALIKE_WEIGHTS  folder of the ALIKE/ALIKED teacher weights (default: ../shared/data/weights_alike)
  EDGEFEAT_TRACEBACK=1    show the traceback of an internal error instead of its one-line summary

Exit codes: 0 done, 2 bad input (one `error:` line on stderr), 1 internal error, 130 interrupted.
"""


# What the toolkit imports beyond the runtime (pyproject's `toolkit` extra), by import name.
TOOLKIT_EXTRA = "edgefeat[toolkit]"
TOOLKIT_MODULES = ("torch", "onnx", "onnxsim", "safetensors", "fvcore", "torch_pruning", "tqdm", "matplotlib", "evo")


def missing_toolkit_modules() -> list[str]:
    """Import names of the toolkit extra that are not installed (a runtime-only install lacks them all)."""
    import importlib.util

    return [name for name in TOOLKIT_MODULES if importlib.util.find_spec(name) is None]


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineArgumentParser(
        prog="toolkit",
        description="EdgeFeat: put a depthwise-separable, deformable keypoint network on a Jetson TX2 or an x86 CPU.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"edgefeat {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="<command>")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    missing = missing_toolkit_modules()
    if missing:  # checked before any command imports them, so the user reads what to install, not a traceback
        print(f"error: toolkit needs the '{TOOLKIT_EXTRA}' extra (missing: {', '.join(missing)}): "
              f"pip install '{TOOLKIT_EXTRA}'; the VO alone runs as python -m vo_runtime", file=sys.stderr)
        return 2
    if hasattr(sys.stdout, "reconfigure") and not sys.stdout.isatty():
        # a log file or a pipe: each line when it is printed, not a buffer's worth at exit
        sys.stdout.reconfigure(line_buffering=True)
    return run_guarded(build_parser(), argv, user_errors())


if __name__ == "__main__":
    sys.exit(main())
