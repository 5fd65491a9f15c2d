"""`toolkit` entry point: one subcommand per module, each registering its own parser.

A subcommand module (``toolkit/cmd_<name>.py``) exposes ``register(subparsers)`` which adds a parser
whose ``func(args) -> int`` does the work. Adding a command is one line in ``COMMAND_MODULES``.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from toolkit import __version__
from toolkit.errors import ToolkitError
from vo_runtime.errors import VORuntimeError

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
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="toolkit",
        description="EdgeFeat: put a depthwise-separable, deformable keypoint network on a Jetson TX2 or an x86 CPU.",
        epilog="Run `toolkit <command> --help` for the options and examples of each command.",
    )
    parser.add_argument("--version", action="version", version=f"edgefeat {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="<command>")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ToolkitError, VORuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
