"""False flags of ``imupipe survey``'s fleet rules on clean simulated fleets, and planted events
still caught on planted ones (issue #30: "flags nothing else on a clean fleet").

For each seed a fleet is simulated (``imupipe simulate fleet``) and surveyed in memory: each log's
IMU tables go through the survey's own still-period detector and figures
(:func:`imupipe.stages.survey.stats.still_periods`, :func:`~imupipe.stages.survey.stats.period_stats`:
the streaming code run as one batch, what ``survey_topic`` runs on a log that fits a batch), the
rows are the dataset's (:func:`imupipe.pipeline.survey.scan._rows`) and the fleet view is
:func:`imupipe.pipeline.survey.report.fleet_view` with ``k = 5``. Only the MCAP write and read
are skipped (the figures do not depend on them).

Printed per fleet kind (``default``: ``imupipe simulate fleet`` as it is, 4 vehicles x 2 IMUs x 6
logs of 150 s; ``small``: ``logs=5 log_s=100`` as the tests and the tutorial; ``chamber``: the tutorial's chamber fleet, ``chamber=true``, compared with
its chamber calibrations), clean (``events=false``, ``chamber_events=false``) and planted:

- per rule (``step``, ``drift``, ``noise``, ``chamber_offset``, ``chamber_slope``) and figure the
  number of false flags, and the false-alarm rate per device and rule (devices x figures judged);
- the devices flagged falsely, with seed and reason (the first few);
- on planted fleets: each planted event caught by the rule the tests expect (crash: a step of
  ``|a| - g`` at the event's log; noise: both noise rules there; failing: gyro z drift or step
  from that log; chamber offset/slope: its chamber rule on gyro z).

Usage: ``python benchmarks/survey_false_flags.py [--seeds 40] [--first 100] [--kinds default,chamber]
[--no-planted | --planted-only]`` (0.3-0.6 s of CPU per fleet; 2-3 minutes of the shared 2-core
development machine for 40 seeds of one kind, clean and planted).

Measured (2026-11-26; false flags on devices without a planted event, planted events caught):

=================================  ==============================  =========================
fleets                             before                          after
=================================  ==============================  =========================
seeds 0-39, default, clean         0                               0
seeds 0-39, small, clean           1 (gyro z drift, seed 16)       0
seeds 0-39, chamber, clean         4 (3 ``|a| - g`` steps, 1 drift; 0
                                   seeds 22 and 29)
seeds 0-39, planted, 3 kinds       3 false; 295 of 320 caught      0 false; 320 of 320 caught
seeds 100-199, small, clean        19 (15 steps, 4 drifts)         0
seeds 100-199, chamber, clean      9 (6 steps, 3 drifts)           0
=================================  ==============================  =========================

"Caught" is the tests' criterion (the rule and the log); before, every planted device was flagged
but 24 runaway gyros were named from a log early or late and one crash's ``|a| - g`` step (into
a log without a level period) was not compared.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from pathlib import Path
from typing import Any

import pyarrow as pa

SMALL = {"logs": 5, "log_s": 100.0}
KINDS: dict[str, dict[str, Any]] = {
    "default": {},
    "small": dict(SMALL),
    "chamber": {**SMALL, "events": False, "chamber": True},
}


def survey_in_memory(fleet: Any, chambers: Any = None, k: float = 5.0) -> tuple[pa.Table, dict]:
    """The survey dataset and fleet view of a simulated fleet (``FleetLogs``), without files."""
    from imupipe.pipeline.survey.report import fleet_view
    from imupipe.pipeline.survey.scan import SurveyTask, _rows
    from imupipe.readers.table import finite, sensor
    from imupipe.stages.survey.stats import StillOptions, period_stats, still_periods

    opts = StillOptions()
    parts = []
    for recipe in fleet.logs:
        log = recipe.rel.removesuffix(".mcap")
        task = SurveyTask(Path(recipe.rel), log, recipe.vehicle, Path("-"), None, None, {}, "")
        for k_imu, table in enumerate(fleet.tables(recipe)):
            g, a = sensor(table, "gyro"), sensor(table, "accel")
            temp, _ = finite(sensor(table, "temperature"))
            found = still_periods(g.t_ns, g.values, a.values, opts)
            stats = period_stats(
                g.t_ns, g.values, a.values, found, opts, (temp.t_ns, temp.values[:, 0])
            )
            topic = f"/imu{k_imu}/data"
            m = len(stats["start_ns"])
            parts.append(_rows(task, topic, k_imu, None, stats, None, m))
    table = pa.concat_tables(parts)
    return table, fleet_view(table, k, chambers)


def _chambers(fleet: Any) -> Any:
    from imupipe.pipeline.survey.chamber import load_chambers

    folder = Path(tempfile.mkdtemp(prefix="chambers-"))
    from imupipe.pipeline.calibration_file import calibration_json

    for vehicle, doc in fleet.chambers.items():
        (folder / f"{vehicle}.json").write_text(calibration_json(doc))
    return load_chambers(folder)


def caught(event: dict[str, Any], flags: list[dict[str, Any]]) -> bool:
    """Whether a planted event is flagged as tests/test_survey.py expects."""
    log = event["log"].removesuffix(".mcap")
    kinds = {(f["kind"], f["figure"], f["log"]) for f in flags}
    if event["kind"] == "crash":
        return ("step", "accel_norm_error", log) in kinds
    if event["kind"] == "noise":
        return ("noise", "gyro_noise", log) in kinds and ("noise", "accel_noise", log) in kinds
    if event["kind"] == "failing":
        runaway = [f for f in flags if f["figure"] == "gyro_bias_z"]
        return bool(runaway) and min(str(f["log"]) for f in runaway) == log
    kind = "chamber_" + event["kind"]
    return any(f["kind"] == kind and f["figure"] == "gyro_bias_z" for f in flags)


def run(kind: str, seeds: list[int], planted: bool) -> dict[str, Any]:
    from imupipe.pipeline.simulate import simulate

    params = dict(KINDS[kind])
    if not planted:
        params.update(events=False, chamber_events=False)
    false: collections.Counter[tuple[str, str]] = collections.Counter()
    examples: list[str] = []
    judged = collections.Counter()
    events_total = events_caught = 0
    missed: list[str] = []
    for seed in seeds:
        fleet, truth = simulate("fleet", params, seed=seed)
        chambers = _chambers(fleet) if params.get("chamber") else None
        _, view = survey_in_memory(fleet, chambers)
        events = list(truth["events"])
        for dev, info in truth["devices"].items():
            change = (info.get("chamber") or {}).get("planted")
            if change:
                for c in change.split(" and "):
                    events.append({"device_id": dev, "kind": c, "log": ""})
        planted_devices = {e["device_id"] for e in events}
        for d in view["devices"]:
            for rule in ("step", "drift"):
                judged[rule] += 4
            judged["noise"] += 2
            if d.get("chamber"):
                judged["chamber_offset"] += 4
                judged["chamber_slope"] += 4
            if d["device_id"] in planted_devices:
                mine = [e for e in events if e["device_id"] == d["device_id"]]
                for e in mine:
                    events_total += 1
                    if caught(e, d["flags"]):
                        events_caught += 1
                    else:
                        got = sorted({(f["kind"], f["figure"], str(f["log"])) for f in d["flags"]})
                        missed.append(
                            f"seed {seed} {d['device_id']} {e['kind']} at {e['log']}: {got}"
                        )
                continue
            for f in d["flags"]:
                false[(f["kind"], f["figure"])] += 1
                if len(examples) < 12:
                    examples.append(f"seed {seed} {d['device_id']}: {f['why']}")
    return {
        "devices": len(seeds) * int(len(view["devices"])),
        "false": false,
        "judged": judged,
        "examples": examples,
        "events": (events_caught, events_total),
        "missed": missed,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=40, help="fleets per kind (default 40)")
    ap.add_argument("--first", type=int, default=100, help="first seed (default 100)")
    ap.add_argument("--kinds", default="default,small,chamber")
    ap.add_argument("--no-planted", action="store_true", help="only the clean fleets")
    ap.add_argument("--planted-only", action="store_true", help="only the planted fleets")
    args = ap.parse_args()
    seeds = list(range(args.first, args.first + args.seeds))
    for kind in args.kinds.split(","):
        for planted in [
            p for p in (False, True) if not (args.no_planted and p or args.planted_only and not p)
        ]:
            t = time.perf_counter()
            r = run(kind, seeds, planted)
            label = f"{kind} fleet, {'planted' if planted else 'clean'}"
            print(
                f"== {label}: {len(seeds)} seeds ({seeds[0]}..{seeds[-1]}), "
                f"{r['devices']} devices, {time.perf_counter() - t:.0f} s"
            )
            total = sum(r["false"].values())
            print(f"   false flags (devices without a planted event): {total}")
            per_rule = collections.Counter()
            for (rule, _), n in r["false"].items():
                per_rule[rule] += n
            for rule, n_judged in sorted(r["judged"].items()):
                n = per_rule.get(rule, 0)
                print(
                    f"   {rule:15s} {n:4d} false of {n_judged:6d} device-figures judged "
                    f"({100 * n / n_judged:.2f} %)"
                )
            for (rule, figure), n in sorted(r["false"].items()):
                print(f"     {rule} {figure}: {n}")
            for line in r["examples"]:
                print("     e.g.", line)
            if planted:
                c, n = r["events"]
                print(f"   planted events caught: {c} of {n}")
                for line in r["missed"][:10]:
                    print("     missed:", line)


if __name__ == "__main__":
    main()
