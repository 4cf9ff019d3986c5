"""The ``imupipe`` command line: ``run``, ``convert``, ``inspect``, ``simulate``.

Errors in the user's input end the command with one line on stderr (``imupipe: error: ...``)
and exit status 2; any other failure prints one line and exits 1. ``--debug`` shows tracebacks.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from imupipe.pipeline.errors import ImupipeError
from imupipe.pipeline.version import VERSION

COMMANDS = {
    "run": "imupipe.pipeline.run",
    "convert": "imupipe.pipeline.convert_cli",
    "inspect": "imupipe.pipeline.inspect_log",
    "simulate": "imupipe.pipeline.simulate",
}
"""Command -> module with ``add_parser(subparsers)`` and ``main(args) -> int``."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="imupipe",
        description="Calibrate IMUs from CSV, MCAP and ROS bags; inspect every stage in Rerun.",
    )
    parser.add_argument("--version", action="version", version=f"imupipe {VERSION}")
    parser.add_argument(
        "--debug", action="store_true", help="show tracebacks on errors (anywhere on the line)"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS.values():
        try:
            importlib.import_module(module).add_parser(sub)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]  # accepted anywhere on the line
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except ImupipeError as exc:
        if debug:
            raise
        print(f"imupipe: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("imupipe: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place that turns any failure into one line
        if debug:
            raise
        print(
            f"imupipe: error: {type(exc).__name__}: {' '.join(str(exc).split())} "
            "(run with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
