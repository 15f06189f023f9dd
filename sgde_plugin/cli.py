"""The `sgde` command line: a thin dispatcher over `sgde_plugin.commands.<name>` modules.

Each command module defines `HELP` (one line), `add_arguments(parser)` and `run(args) -> int`,
and imports heavy libraries (torch, cv2, zarr) only inside `run`, so `sgde --help` stays fast.
Exit codes: 0 success, 2 bad input (one line on stderr, from InputError or a bad option),
1 internal error, 128 + N when stopped by signal N (SIGINT, SIGTERM; a closed pipe ends quietly).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
import traceback
from collections.abc import Iterator
from contextlib import contextmanager

from .errors import InputError

COMMANDS = ["synth", "validate", "masks", "calibrate", "prior", "eval", "cache", "export", "demo", "bench"]


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr and exit code 2 (no usage block)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        """Print `prog: message` on one line and exit 2."""
        text = " ".join(str(message).split())
        self.exit(2, f"{self.prog}: {text} (see {self.prog} --help)\n")


class Stopped(BaseException):
    """Raised in the main thread when a termination signal arrives, so `finally` blocks run."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum: int, frame) -> None:
    raise Stopped(signum)


@contextmanager
def stop_on_sigterm() -> Iterator[None]:
    """Within the block SIGTERM raises `Stopped` in the main thread (as Ctrl-C raises KeyboardInterrupt),
    so builds stop their workers and `finally` blocks run; elsewhere (not the main thread) a no-op."""
    try:
        previous = signal.signal(signal.SIGTERM, _raise_stopped)
    except ValueError:  # not the main thread (an embedding application): leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, one sub-parser per command module."""
    parser = OneLineParser(prog="sgde", description="Stereo Guided Depth Estimation tools.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=OneLineParser)
    for name in COMMANDS:
        module = importlib.import_module(f"sgde_plugin.commands.{name}")
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def _quiet_stdout() -> None:
    """After a closed pipe (`sgde ... | head`): send what is still buffered nowhere."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):
        pass


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `sgde` console script."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option, already reported on one line (2)
        return exc.code if isinstance(exc.code, int) else 2
    if os.environ.get("SGDE_DEBUG"):  # debug logging of every stage (e.g. the adjustment's passes) on stderr
        logging.basicConfig(level=logging.DEBUG, format="%(name)s: %(message)s")
    try:
        with stop_on_sigterm():
            code = args._run(args)
            sys.stdout.flush()
    except InputError as exc:
        print(f"sgde {args.command}: {exc.line()}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        _quiet_stdout()
        return 128 + signal.SIGPIPE
    except (KeyboardInterrupt, Stopped) as exc:
        signum = exc.signum if isinstance(exc, Stopped) else signal.SIGINT
        print(f"sgde {args.command}: stopped by {signal.Signals(signum).name}; outputs are complete or absent "
              "(a prior build resumes where it stopped)", file=sys.stderr)
        return 128 + signum
    except RecursionError:
        print(f"sgde {args.command}: input nested too deeply", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - the CLI boundary reports internal errors
        if os.environ.get("SGDE_DEBUG"):
            traceback.print_exc()
        first = (str(exc).strip().splitlines() or [""])[0][:300]
        print(f"sgde {args.command}: internal error: {type(exc).__name__}: {first}", file=sys.stderr)
        return 1
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
