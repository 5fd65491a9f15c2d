"""`toolkit vo`: the monocular VO runtime on a sequence, with ATE/RPE against ground truth (see docs/vo.md)."""
from __future__ import annotations

import argparse

from vo_runtime.cli import DESCRIPTION, EPILOG, add_arguments, run


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "vo", help="run the monocular VO on a sequence and evaluate its trajectory",
        description=DESCRIPTION, epilog=EPILOG.format(prog="toolkit vo"),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(parser)
    parser.set_defaults(func=run)
