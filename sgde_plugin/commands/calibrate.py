"""`sgde calibrate`: not implemented yet (see the open issue)."""

from __future__ import annotations

import argparse
import sys

HELP = "(not implemented yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No arguments until the command exists."""
    parser.add_argument("rest", nargs=argparse.REMAINDER)


def run(args: argparse.Namespace) -> int:
    """Say the command does not exist yet and fail."""
    print("sgde calibrate: not implemented yet", file=sys.stderr)
    return 1
