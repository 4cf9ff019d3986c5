"""The ``imupipe convert`` command line (the work itself: :func:`imupipe.pipeline.convert.fleet.convert`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from imupipe.pipeline.convert.options import DEFAULT_BATCH_ROWS, ENGINES, ON_MISMATCH
from imupipe.pipeline.errors import one_line


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "convert",
        help="apply a saved calibration to many logs (files or folders), locally or on Ray",
        description=(
            "Apply CAL.json to every log (files, or folders searched recursively for .mcap, .bag, "
            "ROS 2 bag folders and, with --config, .csv) and write DIR/<stem>.mcap per log."
        ),
    )
    p.add_argument(
        "logs",
        nargs="+",
        metavar="LOG",
        help="log files or folders, or objects and prefixes on an object store (s3://BUCKET/KEY)",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        required=True,
        metavar="CAL.json",
        help="a calibration.json (from imupipe run, or attached to a converted MCAP)",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output folder, or a prefix on an object store (s3://BUCKET/PREFIX)",
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="READ.toml",
        help="TOML with how to read the logs: imu_topic, mag_topic, temperature_topic, time and a "
        "[csv] or [fields] mapping (the keys of an [inputs.NAME] table); also makes folders "
        "yield .csv files",
    )
    p.add_argument(
        "--engine", choices=ENGINES, default="local", help="where to run (default local)"
    )
    p.add_argument(
        "--jobs",
        "-j",
        type=int,
        metavar="N",
        default=None,
        help="worker processes (default: the CPUs available); with --engine ray and no "
        "--address, the CPUs of the local Ray it starts",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster: 'auto' (the cluster of this machine) or ray://HOST:10001; "
        "default: start a local Ray",
    )
    p.add_argument(
        "--retries",
        type=int,
        default=2,
        metavar="N",
        help="retries of a log after a crash (default 2)",
    )
    p.add_argument(
        "--batch-rows",
        type=int,
        metavar="ROWS",
        default=DEFAULT_BATCH_ROWS,
        help=f"rows per streamed batch (default {DEFAULT_BATCH_ROWS})",
    )
    p.add_argument(
        "--dashboard",
        action="store_true",
        help="with --engine ray and no --address: also start Ray's dashboard (on 127.0.0.1)",
    )
    p.add_argument(
        "--parquet",
        action="store_true",
        help="also write DIR/parquet/<stem>.parquet per log (one dataset)",
    )
    p.add_argument(
        "--on-mismatch",
        choices=ON_MISMATCH,
        default="warn",
        help="a log whose topics, frames or instances differ from those the calibration was "
        "fitted on: convert it with a warning (default) or refuse it",
    )
    p.add_argument(
        "--read-truncated",
        action="store_true",
        help="read an MCAP or ROS 1 log that is cut off up to the cut, with a warning naming "
        "the byte where the damage starts and the bytes skipped (default: refuse it)",
    )
    p.add_argument("--force", action="store_true", help="convert again even if already done")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from imupipe.pipeline.convert.fleet import convert  # checks the options first

    summary = convert(
        args.logs,
        args.calibration,
        args.out,
        config=args.config,
        engine=args.engine,
        jobs=args.jobs,
        address=args.address,
        retries=args.retries,
        parquet=args.parquet,
        force=args.force,
        batch_rows=args.batch_rows,
        quiet=args.quiet,
        dashboard=args.dashboard,
        on_mismatch=args.on_mismatch,
        read_truncated=args.read_truncated,
    )
    for path, why in summary.failed:
        line = f"{path}: {why}" if path not in why else why
        print(f"imupipe: error: {one_line(line)}", file=sys.stderr)
    if not args.quiet:
        total = len(summary.converted) + len(summary.skipped) + len(summary.failed)
        print(
            f"imupipe convert: {len(summary.converted)} converted, {len(summary.skipped)} "
            f"skipped (already done), {len(summary.failed)} failed of {total} logs; "
            f"{summary.messages:,} messages in {summary.seconds:.1f} s -> {summary.out_dir}"
        )
    return 1 if summary.failed else 0
