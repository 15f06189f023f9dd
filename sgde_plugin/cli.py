"""The `sgde` command line: a thin dispatcher over `sgde_plugin.commands.<name>` modules.

Each command module defines `HELP` (one line), `add_arguments(parser)` and `run(args) -> int`,
and imports heavy libraries (torch, cv2, zarr) only inside `run`, so `sgde --help` stays fast.
Exit codes: 0 success, 2 bad input (one line on stderr, from InputError), 1 internal error.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback

from .errors import InputError

COMMANDS = ["synth", "validate", "masks", "calibrate", "prior", "eval", "cache", "export", "demo", "bench"]


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, one sub-parser per command module."""
    parser = argparse.ArgumentParser(prog="sgde", description="Stereo Guided Depth Estimation tools.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        module = importlib.import_module(f"sgde_plugin.commands.{name}")
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `sgde` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args._run(args)
    except InputError as exc:
        print(f"sgde {args.command}: {exc.line()}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sgde {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the CLI boundary reports internal errors
        if os.environ.get("SGDE_DEBUG"):
            traceback.print_exc()
        print(f"sgde {args.command}: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
