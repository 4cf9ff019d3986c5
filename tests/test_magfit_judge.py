"""The independent judge of in-flight compass fits (benchmarks/magfit_judge.py): pymavlink's
field, the attitude as MagFit reads it (with AHRS_TRIM), MagFit's way of applying parameters.
Reads ../shared/data/logs (skipped where absent); MagFit's own fits are slow (marked)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from conftest import shared_path

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def judge():
    pytest.importorskip("pymavlink")
    spec = importlib.util.spec_from_file_location(
        "magfit_judge", REPO / "benchmarks" / "magfit_judge.py"
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules["magfit_judge"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(
    ("name", "mag", "flown_mg"),
    [
        ("erle_pxf_218", "MAG", 150.7),
        ("erle_pxf_118", "MAG", 198.5),
        ("spark404_utrecht", "MAG", 53.9),
        ("spark404_utrecht", "MAG2", 66.0),
    ],
)
def test_the_judge_reproduces_the_as_flown_figures(judge, name, mag, flown_mg):
    """The vehicle's own calibration scored as issue 35's judge scored it (mG, within 1)."""
    path = shared_path("logs", "ardupilot_flights", *judge.LOGS[name].split("/"))
    f = judge.read_flight(path, mag, judge.WINDOWS.get(name))
    assert judge.score(f, f.params)[0] == pytest.approx(flown_mg, abs=1.0)


def test_imupipe_beats_magfits_figures_on_spark404(judge, tmp_path):
    """spark404_utrecht (AHRS_TRIM_Y 2.1 deg): imupipe's exported file, loaded over the log's
    parameters, scores below MagFit's 25.8 / 11.8 mG (issue 35's judge) on both compasses,
    whole log and held out (before the trim was applied: 20.6 / 20.8 mG), and lowers the heading
    error below as flown."""
    name = "spark404_utrecht"
    path = shared_path("logs", "ardupilot_flights", *judge.LOGS[name].split("/"))
    flights = {m: judge.read_flight(path, m) for m in ("MAG", "MAG2")}
    ours = judge.run_imupipe(path, ["MAG", "MAG2"], tmp_path / "whole")
    assert not isinstance(ours, str), ours
    first = judge.cut_log(flights["MAG"], tmp_path / "first" / path.name)
    held = judge.run_imupipe(first, ["MAG", "MAG2"], tmp_path / "held")
    assert not isinstance(held, str), held
    for mag, magfit_mg in (("MAG", 25.8), ("MAG2", 11.8)):
        f = flights[mag]
        flown = judge.score(f, f.params)
        whole = judge.score(f, f.params | ours)
        later = judge.score(f, f.params | held, judge.held_rows(f))
        assert whole[0] < magfit_mg and whole[1] < flown[1], (mag, whole)
        assert later[0] < magfit_mg, (mag, later)


@pytest.mark.slow
def test_no_worse_than_magfit_on_spark404_held_out(judge, tmp_path):
    """MagFit itself (magfit_WMM.py --elliptical, minutes) on the first 60 % of spark404's MAG,
    scored on the last 40 % beside imupipe's fit of the same part."""
    name = "spark404_utrecht"
    rows = judge.judge_log(name, tmp_path)
    for r in rows:
        if isinstance(r.magfit_held, str):
            continue
        assert r.imupipe_held[0] <= r.magfit_held[0], r


@pytest.mark.parametrize(
    ("name", "magfit_mg", "magfit_deg"),
    [("erle_pxf_218", 32.2, 6.48), ("forum13645_ac344", 5.8, 0.63)],
)
def test_held_out_no_worse_than_magfit_on_a_flight_of_little_tilt(
    judge, tmp_path, name, magfit_mg, magfit_deg
):
    """Fitted on the first 60 % of the log (tilt to 10-12 deg: field directions below
    min_spread), imupipe's MAG file scored on the last 40 % is at or below MagFit's bounded fit
    of the same part (its figures on this judge, MagFit run as benchmarks/bench_magfit.py --real
    runs it), the heading within MagFit's + 0.3 deg. Before, the soft iron was not a candidate
    on such a part and the scale lost: 32.9 mG and 8.0 mG, 1.54 deg."""
    path = shared_path("logs", "ardupilot_flights", *judge.LOGS[name].split("/"))
    f = judge.read_flight(path, "MAG", judge.WINDOWS.get(name))
    first = judge.cut_log(f, tmp_path / "first" / path.name)
    held = judge.run_imupipe(first, ["MAG"], tmp_path / "held")
    assert not isinstance(held, str), held
    residual, heading = judge.score(f, f.params | held, judge.held_rows(f))
    assert residual <= magfit_mg and heading <= magfit_deg + 0.3, (residual, heading)
