"""imupipe's ``mag_inflight`` against pymavlink's MagFit (``tools/magfit_WMM.py``) on the same
DataFlash logs: a simulated flight with a known compass error (``imupipe simulate flight``),
scored as below, and the real flights of ../shared/data/logs (ArduPilot and PX4), judged by
:mod:`magfit_judge` with pymavlink's own instruments (its field table, the attitude with
``AHRS_TRIM``, MagFit's way of applying parameters to the exported files), whole log and held
out (``--real``; the docs' table in docs/explanation/benchmarks.md).

MagFit runs headless (``MPLBACKEND=Agg``, ``--elliptical``, ``--cmot`` where the log has a
current, ``--att-source ATT``, ``--save-params``); its parameters are applied as it applies them
(``correct``: ``W s (raw + OFS) + MOT I`` on the raw field, i.e. the logged field with the
log's own ``COMPASS_*`` removed as its ``remove_offsets`` does). Both corrections are then
scored the same way, on the same samples: the RMS vector residual against the WMM field of the
flight's date rotated into the body by ``ATT`` (uT) and the RMS heading error (deg).

Usage: ``python benchmarks/bench_magfit.py [--reduce 5] [--iter 300] [--cache DIR] [--real]``
(MagFit is pure Python: minutes per log; ``--cache`` keeps its parameter files).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.dataflash.reader import DataFlashLog, read_dataflash
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import finite, metadata, sensor
from imupipe.stages.base import StageContext
from imupipe.stages.magnetometer.inflight import (
    MagInflightStage,
    flight_samples,
    heading_deg,
    wrap_deg,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "logs" / "ardupilot_flights"
REAL = {
    "erle_pxf_118/118.BIN": {},
    "erle_pxf_218/218.BIN": {},
    "forum13645_ac344/log_0036.bin": {"imu_topic": "IMU", "mag_topic": "MAG"},
    "spark404_utrecht/log.bin": {"imu_topic": "IMU", "mag_topic": "MAG"},
}


def magfit_script() -> Path:
    import pymavlink

    return Path(pymavlink.__file__).parent / "tools" / "magfit_WMM.py"


def run_magfit(
    path: Path, cmot: bool, reduce: int, iters: int, cache: Path | None
) -> dict[str, float] | str:
    """MagFit's new parameters, or why it did not run (kept in, and reused from, ``cache``)."""
    out = path.with_name(path.name.rsplit(".", 1)[0] + "-magfit-mag-1.param")
    kept = None if cache is None else cache / f"{path.parent.name}-{out.name}"
    if kept is not None and kept.exists():
        return _params(kept)
    args = [sys.executable, str(magfit_script()), "--elliptical", "--save-params"]
    args += ["--reduce", str(reduce), "--iter", str(iters), "--att-source", "ATT"]
    args += ["--cmot"] if cmot else []
    env = dict(os.environ, MPLBACKEND="Agg")
    proc = subprocess.run([*args, str(path)], capture_output=True, text=True, env=env, timeout=3600)
    if proc.returncode != 0 or not out.exists():
        said = (proc.stderr + proc.stdout).strip().splitlines()
        return ([line for line in said if "fail" in line.lower()] or said or ["no output"])[-1]
    if kept is not None:
        kept.write_text(out.read_text())
    return _params(out)


def _params(path: Path) -> dict[str, float]:
    params = {}
    for line in path.read_text().splitlines():
        name, value = line.split()
        params[name] = float(value)
    return params


def _vec(p: dict[str, float], name: str, default: float) -> np.ndarray:
    return np.array([p.get(f"{name}_{a}", default) for a in "XYZ"])


def _matrix(p: dict[str, float]) -> np.ndarray:
    d, o = _vec(p, "COMPASS_DIA", 1.0), _vec(p, "COMPASS_ODI", 0.0)
    if not d.any():
        d = np.ones(3)
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


def magfit_corrected(
    path: Path, t_ns: np.ndarray, logged: np.ndarray, current, new: dict[str, float]
) -> np.ndarray:
    """MagFit's correction of the samples at ``t_ns`` (T): the log's own compass correction
    removed (``remove_offsets``), then the new one applied (``correct``)."""
    f = DataFlashLog(path)
    old = f.parameters()
    t_mag = f.time_ns("MAG")
    order = np.argsort(t_mag, kind="stable")
    at = order[np.searchsorted(t_mag[order], t_ns)]
    ofs_logged = np.column_stack([f.field("MAG", f"Ofs{a}")[at] for a in "XYZ"])
    mg = logged * 1e7
    amps = np.zeros(len(mg)) if current is None else current
    if old.get("COMPASS_MOTCT", 0) == 2:
        mg = mg - amps[:, None] * _vec(old, "COMPASS_MOT", 0.0)
    scale = old.get("COMPASS_SCALE") or 1.0
    raw = np.linalg.solve(_matrix(old), mg.T).T / scale - ofs_logged
    fixed = (raw + _vec(new, "COMPASS_OFS", 0.0)) * new.get("COMPASS_SCALE", 1.0)
    fixed = fixed @ _matrix(new).T
    if new.get("COMPASS_MOTCT", 0) == 2:
        fixed = fixed + amps[:, None] * _vec(new, "COMPASS_MOT", 0.0)
    return fixed * 1e-7


def score(fs, corrected: np.ndarray) -> tuple[float, float]:
    """RMS vector residual (uT) and RMS heading error (deg) against the WMM."""
    r = np.linalg.norm(corrected - fs.target, axis=1) * 1e6
    h = wrap_deg(heading_deg(fs.q, corrected) - heading_deg(fs.q, fs.target))
    return float(np.sqrt(np.mean(r**2))), float(np.sqrt(np.mean(h**2)))


def compare(path: Path, spec: dict, reduce: int, iters: int, cache: Path | None) -> None:
    table, _ = read_dataflash(InputSpec(path=path, **spec))
    stage = MagInflightStage(MagInflightStage.Options())
    ctx = StageContext(name="mag_inflight", input_name=path.name, quiet=True)
    out = stage.fit(table, ctx)
    mag, _ = finite(sensor(table, "mag"))
    fs = flight_samples(table, mag, float(metadata(table)["gps_year"]))
    ours = out.step.apply_values(fs.raw)
    power = fs.power(out.results["motor_source"])  # the current or the throttle (or none)
    if power is not None:
        ours = ours + power[:, None] * out.step.motor
    before, ours_s = score(fs, fs.raw), score(fs, ours)
    varies = fs.current is not None and np.ptp(fs.current) > 1.0
    mf = run_magfit(path, varies, reduce, iters, cache)
    if isinstance(mf, str):
        theirs = f"MagFit did not run: {mf}"
    else:
        t = score(fs, magfit_corrected(path, fs.t_ns, fs.raw, fs.current, mf))
        theirs = f"MagFit {t[0]:6.2f} uT {t[1]:5.2f} deg"
    print(
        f"{path.parent.name + '/' + path.name:34s} n={len(fs.t_ns):5d} "
        f"before {before[0]:6.2f} uT {before[1]:5.2f} deg | imupipe ({out.results['model']}"
        f"{'+' + out.results['motor_source'] if out.results['motor_term'] else ''}) "
        f"{ours_s[0]:6.2f} uT "
        f"{ours_s[1]:5.2f} deg | {theirs}",
        flush=True,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", help="real logs under ardupilot_flights (default: all)")
    ap.add_argument("--reduce", type=int, default=5, help="MagFit's --reduce")
    ap.add_argument("--iter", type=int, default=300, help="MagFit's --iter")
    ap.add_argument("--cache", type=Path, help="keep MagFit's .param files here (and reuse them)")
    ap.add_argument("--real", action="store_true", help="the independent judge's tables only")
    ap.add_argument("--px4", action="store_true", help="the PX4 flights' table only")
    args = ap.parse_args()
    if args.px4:
        sys.path.insert(0, str(Path(__file__).parent))
        import magfit_judge as judge

        with tempfile.TemporaryDirectory() as tmp:
            print("\n".join(judge.judge_px4(Path(tmp) / "px4")))
        return
    if args.real:
        sys.path.insert(0, str(Path(__file__).parent))
        import magfit_judge as judge

        with tempfile.TemporaryDirectory() as tmp:
            rows = []
            for name in args.logs or judge.LOGS:
                if not (judge.SHARED / judge.LOGS[name]).exists():
                    print(f"{name}: not present")
                    continue
                rows += judge.judge_log(name, Path(tmp), args.reduce, args.iter, args.cache)
            print(judge.markdown(rows), flush=True)
            if judge.PX4.exists():
                print("\n".join(judge.judge_px4(Path(tmp) / "px4")))
        return
    with tempfile.TemporaryDirectory() as tmp:
        sim_dir = Path(tmp) / "simulated"
        sim_dir.mkdir()
        sim = sim_dir / "flight.bin"
        table, _ = simulate("flight", {"duration_s": 120.0}, seed=3)
        write_log(sim, table)
        compare(sim, {}, args.reduce * 2, args.iter, args.cache)
        for name in args.logs or REAL:
            path = SHARED / name
            if not path.exists():
                print(f"{name}: not present ({path})")
                continue
            copy = Path(tmp) / path.parent.name / path.name  # MagFit writes beside the log
            copy.parent.mkdir()
            copy.write_bytes(path.read_bytes())
            compare(copy, REAL.get(name, {}), args.reduce, args.iter, args.cache)


if __name__ == "__main__":
    main()
