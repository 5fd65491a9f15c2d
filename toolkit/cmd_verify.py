"""`toolkit verify`: the runtime's ``python -m vo_runtime verify``, for a shell that has the toolkit."""
from __future__ import annotations

import argparse

from vo_runtime.verify import DESCRIPTION, EPILOG, add_arguments, run


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "verify",
        help="run an artefact's reference inputs on a provider or TensorRT engine, compare with its parity run",
        description=DESCRIPTION,
        epilog=EPILOG.format(prog="toolkit verify"),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(parser)
    parser.set_defaults(func=run)
