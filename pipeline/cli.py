"""The ``imupipe`` command line: ``run``, ``convert``, ``inspect``, ``simulate``, ``import``.

**One error contract.** A problem with the user's input or environment ends the command with one
line on stderr (``imupipe: error: ...``) naming the file or key, and exit status 2: an
:class:`~imupipe.readers.errors.ImupipeError`, or an ``OSError`` of the file system (disk full,
permission denied, read-only folder, busy file; the line names the file). Exit status 1 is kept
for ``convert`` when some logs of a fleet failed, and for bugs, which also print one line
(``--debug`` prints the traceback before the line; the exit status stays the same). SIGINT
exits 130, SIGTERM 143; both remove the command's temporary files first.

**Start-up.** Only the module of the command given is imported (``imupipe --help`` imports
none), so the command line starts in a few tens of milliseconds. The ``imupipe`` program
(:func:`console`) also spares the interpreter's exit a walk over every object (issue 39).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import sys
import traceback

from imupipe.pipeline.errors import ImupipeError, one_line
from imupipe.pipeline.signals import (
    Terminated,
    exit_on_sigterm,
    terminate_on_sigterm,
    was_terminated,
)

exit_on_sigterm()  # a SIGTERM before main() runs: status 143, as after it

COMMANDS: dict[str, tuple[str, str]] = {
    "run": (
        "imupipe.pipeline.run",
        "calibrate: read the inputs, run the stages, write the outputs",
    ),
    "convert": (
        "imupipe.pipeline.convert.cli",
        "apply a saved calibration to many logs (files or folders), locally or on Ray",
    ),
    "inspect": (
        "imupipe.pipeline.inspect_log",
        "topics, types, counts, rates and the columns a log fills",
    ),
    "simulate": (
        "imupipe.pipeline.simulate",
        "write a synthetic log with a known truth (static, poses, mag, thermal, thermal_soak, camera, "
        "board, flight, fleet)",
    ),
    "survey": (
        "imupipe.pipeline.survey.scan",
        "every still moment of a fleet's logs: each IMU's bias, noise, temperature over time",
    ),
    "import": (
        "imupipe.pipeline.imports",
        "make a calibration.json from another tool's calibration (Kalibr, imu_tk, Magneto)",
    ),
}
"""Command -> (module with ``add_parser(subparsers)`` and ``main(args) -> int``, one-line help)."""


EAGER_COMMIT = "0"
"""mimalloc's ``arena_eager_commit`` for a command (``MIMALLOC_ARENA_EAGER_COMMIT``, unless the
user set it): its memory committed as it is first used, not each 1 GiB arena at once.
Committed eagerly (mimalloc's default on Linux), the arena's memory is backed by transparent
huge pages: pyarrow's CSV parse of the 2 h, 400 Hz log (412 MB) then left 690 MB in huge pages
and cost 0.8-2.0 s of kernel time on the 2-core test machine, a VM on which a fresh huge page
is faulted back in from the host (see :func:`imupipe.readers.table_buffer.small_pages`),
against 0.35-0.65 s in 4 KiB pages, the user time the same (fresh processes, alternated); a
whole ``imupipe run`` of it with one ``allan`` stage took 0.92x the CPU (median of 8 alternated
pairs, load 4.5). Memory only: no value changes."""


class _Version(argparse.Action):
    """``--version``, reading the installed version only when asked."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, help="show the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        from imupipe.pipeline.version import VERSION

        parser.exit(message=f"imupipe {VERSION}\n")


def _command(argv: list[str]) -> str | None:
    """The command named on the line (the first word that is not an option)."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported, and the other commands get their help
    line only when no known command is given (a known command's line never shows them: 1-2 ms
    of a one-log ``convert``, issue 39)."""
    parser = argparse.ArgumentParser(
        prog="imupipe",
        description=(
            "Calibrate IMUs from CSV, MCAP, ROS bags, PX4 ULog and ArduPilot DataFlash; inspect every "
            "stage in Rerun."
        ),
    )
    parser.add_argument("--version", action=_Version)
    parser.add_argument(
        "--debug", action="store_true", help="show tracebacks on errors (anywhere on the line)"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_line) in COMMANDS.items():
        if name == command:
            importlib.import_module(module).add_parser(sub)
        elif command not in COMMANDS:
            sub.add_parser(name, help=help_line, add_help=False)
    return parser


def _os_error(exc: OSError) -> str:
    """One line for a file-system error: the file and what is wrong."""
    what = exc.strerror or type(exc).__name__
    if exc.filename is None:
        return what
    if exc.filename2 is not None:
        return f"{exc.filename} -> {exc.filename2}: {what}"
    return f"{exc.filename}: {what}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]  # accepted anywhere on the line
    if not debug:  # Rerun's own (Rust) log lines are for its developers; read before rerun loads
        os.environ.setdefault("RUST_LOG", "off")
    # read by mimalloc (pyarrow's default memory pool, Rerun's allocator) when it starts, before
    # pyarrow loads: see EAGER_COMMIT
    os.environ.setdefault("MIMALLOC_ARENA_EAGER_COMMIT", EAGER_COMMIT)
    terminate_on_sigterm()
    try:
        args = build_parser(_command(argv)).parse_args(argv)
        code = int(args.func(args) or 0)
        exit_on_sigterm()  # the outputs are in place: nothing left to clean up
        if was_terminated():  # its Terminated was swallowed (raised in a finaliser)
            raise Terminated()
        return code
    except ImupipeError as exc:
        return _error(str(exc), exc.exit_code, debug)
    except OSError as exc:  # the file system: disk full, permissions, read-only, busy
        return _error(_os_error(exc), 2, debug)
    except KeyboardInterrupt:
        print("imupipe: interrupted", file=sys.stderr)
        return 130
    except Terminated as exc:
        print("imupipe: terminated", file=sys.stderr)
        return exc.exit_code
    except Exception as exc:  # noqa: BLE001 - the one place that turns any failure into one line
        line = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        return _error(line if debug else f"{line} (run with --debug for the traceback)", 1, debug)


def _error(line: str, code: int, debug: bool) -> int:
    """Print the error line (after the traceback with ``--debug``); the exit status is the same
    with and without ``--debug``."""
    if debug:
        traceback.print_exc()
    print(f"imupipe: error: {one_line(line)}", file=sys.stderr)
    return code


def console() -> None:
    """The ``imupipe`` program: :func:`main` on ``sys.argv``, then exit with its status.

    Before the interpreter exits, the objects still alive are frozen (:func:`gc.freeze`), so
    that the last cyclic garbage collection of its exit does not walk every object of every
    module loaded (numpy's, pyarrow's, imupipe's): 20-25 ms of CPU, a third of a one-log
    ``convert``'s own cost (issue 39). The command is over by then: its outputs are written,
    closed and renamed, its temporary files removed; ``atexit`` handlers (and the
    ``weakref.finalize`` callbacks they run) still run, and objects are still freed when their
    last reference goes. :func:`main` itself leaves the collector alone (it is also called
    in-process, by tests)."""
    code = main()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    console()
