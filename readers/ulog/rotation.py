"""PX4's board and sensor rotations (``SENS_BOARD_ROT``, ``CAL_MAGn_ROT``): the enum, its
matrices, and the rotation PX4 applies to a magnetometer after its calibration.

PX4 (``src/lib/conversion/rotation.h``, ``get_rot_matrix``) numbers each rotation and defines it
by roll, pitch and yaw in whole degrees; its matrix is the direction cosine matrix of those Euler
angles, ``Rz(yaw) Ry(pitch) Rx(roll)``, mapping the sensor's (board's) axes onto the vehicle's
body axes. ArduPilot's ``Rotation`` enum (``AHRS_ORIENTATION``, ``COMPASS_ORIENT``) has the same
numbers and rotations for 0..40.

The magnetometer (``src/lib/sensor_calibration/Magnetometer.cpp``, ``Correct``)::

    body = R (S ((raw + power COMP) - OFF)),    R = Euler(SENS_BOARD_{X,Y,Z}_OFF) rot(enum)

``enum`` is ``CAL_MAGn_ROT`` for an external magnetometer and ``SENS_BOARD_ROT`` for an internal
one (PX4 keeps an internal magnetometer's ``CAL_MAGn_ROT`` at -1). The level adjustment
``SENS_BOARD_{X,Y,Z}_OFF`` (degrees) applies to internal magnetometers in every PX4 version and
to external ones from v1.13 (``Magnetometer::set_rotation``); imupipe applies it to both.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

ROTATIONS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270),
    (0, 0, 315), (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0),
    (180, 0, 225), (180, 0, 270), (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90),
    (90, 0, 135), (270, 0, 0), (270, 0, 45), (270, 0, 90), (270, 0, 135), (0, 90, 0),
    (0, 270, 0), (0, 180, 90), (0, 180, 270), (90, 90, 0), (180, 90, 0), (270, 90, 0),
    (90, 180, 0), (270, 180, 0), (90, 270, 0), (180, 270, 0), (270, 270, 0), (90, 180, 90),
    (90, 0, 270), (90, 68, 293), (0, 315, 0), (90, 315, 0), (270, 0, 180), (270, 0, 270),
    (0, 90, 180), (0, 9, 180), (0, 45, 0), (270, 0, 225), (270, 0, 315),
)  # fmt: skip
"""PX4's rotation ``k`` (the enum value) -> (roll, pitch, yaw) in degrees."""


def euler_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The direction cosine matrix ``Rz(yaw) Ry(pitch) Rx(roll)`` (radians): body <- sensor."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (np.cos, np.sin))
    return np.array(
        [
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [-sp, sr * cp, cr * cp],
        ]
    )


def rotation_matrix(k: int) -> np.ndarray:
    """The matrix of PX4 rotation ``k`` (exact: entries rounded to 1e-12). ValueError for a
    number PX4 does not define."""
    if not 0 <= int(k) < len(ROTATIONS):
        raise ValueError(f"rotation {k} is not one of PX4's 0..{len(ROTATIONS) - 1}")
    m = euler_matrix(*np.radians(ROTATIONS[int(k)]))
    return np.where(np.abs(m) < 1e-12, 0.0, m)


def mag_rotation(params: Mapping[str, Any], slot: int) -> tuple[np.ndarray, dict[str, float]]:
    """(R, the parameters it was made of) of PX4's magnetometer calibration slot ``slot``
    (module docstring): external (``CAL_MAGn_ROT`` >= 0) or internal (-1, or unset: the board's
    ``SENS_BOARD_ROT``), then the level adjustment. ValueError for an undefined rotation."""
    rot = int(params.get(f"CAL_MAG{slot}_ROT", -1))
    used: dict[str, float] = {f"CAL_MAG{slot}_ROT": rot}
    if rot < 0:
        rot = int(params.get("SENS_BOARD_ROT", 0) or 0)
        used["SENS_BOARD_ROT"] = rot
    level = [float(params.get(f"SENS_BOARD_{a}_OFF", 0.0) or 0.0) for a in "XYZ"]
    used |= {f"SENS_BOARD_{a}_OFF": v for a, v in zip("XYZ", level, strict=True) if v}
    return euler_matrix(*np.radians(level)) @ rotation_matrix(rot), used


def mag_slot(params: Mapping[str, Any], device_id: int | None) -> int | None:
    """The ``CAL_MAGn`` slot whose ``CAL_MAGn_ID`` is ``device_id``; None when none is."""
    if device_id is None:
        return None
    return next((n for n in range(4) if params.get(f"CAL_MAG{n}_ID") == device_id), None)
