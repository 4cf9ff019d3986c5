"""The earth's magnetic field from the World Magnetic Model (NOAA/NCEI and BGS), through the
``pygeomag`` package (MIT; pure Python; ships every WMM epoch since 2010, so that logs flown
years ago get the model of their own date).

``earth_field(lat_deg, lon_deg, alt_m, t_ns)`` gives the field in the local NED frame, tesla.
The model is evaluated at most :data:`MAX_EVALUATIONS` times along a flight (evenly in sample
order) and interpolated linearly between: over a flight of a few kilometres the field changes
by a few nT, far below any magnetometer's noise.
"""

from __future__ import annotations

import datetime as dt

import numpy as np

MAX_EVALUATIONS = 64
"""Points along a flight where the model is evaluated (the rest are interpolated)."""
NANOTESLA = 1e-9
EPOCHS = {2010: "wmm/WMM_2010.COF", 2015: "wmm/WMM_2015v2.COF", 2020: "wmm/WMM_2020.COF"}
"""Model epoch -> pygeomag's coefficient file; later dates use its current model."""


def decimal_year(t_ns: np.ndarray) -> np.ndarray:
    """UTC decimal years of Unix times (int64 ns)."""
    seconds = np.asarray(t_ns, dtype=np.float64) * 1e-9
    years = 1970.0 + seconds / (365.2425 * 86400.0)
    return years


def date_of(year: float) -> str:
    """The UTC date (``YYYY-MM-DD``) of a decimal year in :func:`decimal_year`'s scale (the
    readers' ``gps_year``)."""
    seconds = (float(year) - 1970.0) * 365.2425 * 86400.0
    return (dt.datetime(1970, 1, 1, tzinfo=dt.UTC) + dt.timedelta(seconds=seconds)).strftime(
        "%Y-%m-%d"
    )


def _model(year: float):  # type: ignore[no-untyped-def]
    from pygeomag import GeoMag

    epoch = max((e for e in EPOCHS if e <= year), default=None)
    if epoch is None or year >= 2025:
        return GeoMag()
    return GeoMag(coefficients_file=EPOCHS[epoch])


def earth_field(
    lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray, year: float
) -> np.ndarray:
    """(n, 3) WMM field (north, east, down) in tesla at the given WGS-84 positions on the
    decimal ``year`` (one date per flight: the secular change over a flight is negligible).
    ValueError when the year is outside every model's span (before 2010)."""
    lat, lon, alt = (np.asarray(a, dtype=np.float64) for a in (lat_deg, lon_deg, alt_m))
    n = len(lat)
    if n == 0:
        return np.zeros((0, 3))
    if year < 2010.0:
        raise ValueError(f"date {year:.2f} is before the first World Magnetic Model (2010)")
    model = _model(year)
    idx = np.unique(np.linspace(0, n - 1, min(n, MAX_EVALUATIONS)).round().astype(int))
    at = np.array(
        [_evaluate(model, float(lat[i]), float(lon[i]), float(alt[i]), year) for i in idx]
    )
    if len(idx) == 1:
        return np.tile(at[0], (n, 1))
    k = np.arange(n, dtype=np.float64)
    return np.column_stack([np.interp(k, idx, at[:, j]) for j in range(3)])


def _evaluate(model, lat: float, lon: float, alt_m: float, year: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    r = model.calculate(
        glat=lat, glon=lon, alt=alt_m / 1000.0, time=year, allow_date_outside_lifespan=True
    )
    return np.array([r.x, r.y, r.z]) * NANOTESLA


def year_of(when: dt.datetime) -> float:
    """The decimal year of a date."""
    start = dt.datetime(when.year, 1, 1, tzinfo=when.tzinfo)
    end = dt.datetime(when.year + 1, 1, 1, tzinfo=when.tzinfo)
    return when.year + (when - start) / (end - start)
