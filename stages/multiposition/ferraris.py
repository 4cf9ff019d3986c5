"""Ferraris calibration (Ferraris et al. 1995, as implemented by imucal's ``FerrarisCalibration``):
six static poses (each axis parallel ``_p`` and antiparallel ``_a`` to gravity) and three turns of
a known angle about each axis (``_rot``) give accelerometer and gyroscope scale, rotation and bias
in closed form.

Model (raw units in, m/s^2 and deg/s out, as imucal)::

    a = R_a^-1 K_a^-1 (a_raw - b_a)
    w = R_g^-1 K_g^-1 (w_raw - b_g - K_ga a)

Equations (imucal's numbering): U_p, U_n the 3x3 matrices whose columns are the mean raw
accelerometer in the x/y/z ``_p`` and ``_a`` poses; ``b_a = diag((U_p + U_n) / 2)`` (19-20);
``K_a = diag(sqrt(diag(D D^T)) / (2 g))``, ``R_a = K_a^-1 D / (2 g)`` with ``D = U_p - U_n``
(21-23); ``b_g`` the mean gyro over all six static poses; ``K_ga = (G_p - G_n) / (2 g)`` from the
gyro means (9); each turn's gyro, with offsets ``b_g + K_ga a`` removed, is summed and divided by
the sample rate into the columns of ``W`` (13-14); ``M = W / angle``, ``K_g = diag(sqrt(diag(M
M^T)))``, ``R_g = K_g^-1 M`` (12, 15).

The chain applies this as three steps: the accelerometer's linear step, then (on request)
:class:`GSensitivityStep`, ``w_raw - K_ga a`` with ``a`` the *calibrated* accelerometer of the
same sample, then the gyroscope's linear step ``R_g^-1 K_g^-1 (w - b_g)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.table import has_stream, imu_pairs, replace_sensor
from imupipe.stages.steps import Step

STATIC_PARTS = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
ROTATION_PARTS = ("x_rot", "y_rot", "z_rot")


@dataclass(frozen=True)
class FerrarisResult:
    """imucal's fields (raw -> m/s^2 and deg/s)."""

    K_a: np.ndarray  # noqa: N815 (the publication's names)
    R_a: np.ndarray  # noqa: N815
    b_a: np.ndarray
    K_g: np.ndarray  # noqa: N815
    R_g: np.ndarray  # noqa: N815
    K_ga: np.ndarray  # noqa: N815
    b_g: np.ndarray

    @property
    def accel_matrix(self) -> np.ndarray:
        return np.linalg.inv(self.R_a) @ np.linalg.inv(self.K_a)

    @property
    def gyro_matrix_dps(self) -> np.ndarray:
        return np.linalg.inv(self.R_g) @ np.linalg.inv(self.K_g)

    def calibrate_acc(self, acc: np.ndarray) -> np.ndarray:
        return (acc - self.b_a) @ self.accel_matrix.T

    def gyro_offsets(self, calibrated_acc: np.ndarray) -> np.ndarray:
        """``b_g + K_ga a`` (n, 3), raw gyro units."""
        return calibrated_acc @ self.K_ga.T + self.b_g

    def to_json(self) -> dict[str, list]:
        return {k: np.asarray(getattr(self, k)).tolist() for k in self.__dataclass_fields__}


def ferraris(
    parts: Mapping[str, tuple[np.ndarray, np.ndarray]],
    sampling_rate_hz: float,
    grav: float = 9.81,
    expected_angle_deg: float = -360.0,
) -> FerrarisResult:
    """Ferraris calibration from ``parts``: name -> (accel (n, 3), gyro (n, 3)) raw samples, for
    the names of :data:`STATIC_PARTS` and :data:`ROTATION_PARTS` (see the module docstring)."""

    def means(kind: int, suffix: str) -> np.ndarray:
        return np.column_stack([parts[f"{a}_{suffix}"][kind].mean(axis=0) for a in "xyz"])

    u_p, u_n = means(0, "p"), means(0, "a")
    b_a = np.diag((u_p + u_n) / 2)
    d = u_p - u_n
    k_a = np.diag(np.sqrt(np.diag(d @ d.T) / (4 * grav**2)))
    r_a = np.linalg.inv(k_a) @ d / (2 * grav)

    b_g = np.vstack([parts[p][1] for p in STATIC_PARTS]).mean(axis=0)
    k_ga = (means(1, "p") - means(1, "a")) / (2 * grav)

    partial = FerrarisResult(k_a, r_a, b_a, np.eye(3), np.eye(3), k_ga, b_g)
    w = np.empty((3, 3))
    for i, axis in enumerate("xyz"):
        acc, gyr = parts[f"{axis}_rot"]
        corrected = gyr - partial.gyro_offsets(partial.calibrate_acc(acc))
        w[:, i] = corrected.sum(axis=0) / sampling_rate_hz
    m = w @ np.linalg.inv(expected_angle_deg * np.eye(3))
    k_g = np.diag(np.sqrt(np.diag(m @ m.T)))
    r_g = np.linalg.inv(k_g) @ m
    return FerrarisResult(k_a, r_a, b_a, k_g, r_g, k_ga, b_g)


@dataclass
class GSensitivityStep(Step):
    """``w <- w - K_ga a``: removes the gyroscope's sensitivity to specific force (imucal's
    ``K_ga``, eq. 9), with ``a`` the accelerometer of the same IMU sample *as corrected by the
    chain so far* (m/s^2) and ``w`` the gyro in the units the next (linear) step expects.

    Each sample is corrected from its own accelerometer values, so the default
    :meth:`Step.apply_stream` (every batch on its own) equals :meth:`apply` on the whole log.
    A sample whose accelerometer is not finite keeps its gyro value (nothing to subtract)."""

    kind: ClassVar[str] = "g_sensitivity"
    type: str
    sensor: str
    k_ga: np.ndarray

    def __post_init__(self) -> None:
        self.k_ga = np.asarray(self.k_ga, dtype=np.float64).reshape(3, 3)
        if self.sensor != "gyro":
            raise ValueError(f"a g-sensitivity step corrects the gyro, not {self.sensor}")

    def apply(self, table: pa.Table) -> pa.Table:
        if not has_stream(table, "imu"):
            return table
        gyro, accel, _ = imu_pairs(table)  # sampled apart: the accel on the gyro's stamps
        acc = accel.values
        ok = np.isfinite(acc).all(axis=1)
        # elementwise (not a matrix product, whose rounding depends on the batch size): each
        # sample's result is the same whether the log is corrected whole or batch by batch
        a = np.where(ok[:, None], acc, 0.0)
        offset = (
            a[:, 0:1] * self.k_ga[:, 0] + a[:, 1:2] * self.k_ga[:, 1] + a[:, 2:3] * self.k_ga[:, 2]
        )
        return replace_sensor(table, "gyro", gyro.rows, gyro.values - offset)

    def to_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "sensor": self.sensor,
            "kind": self.kind,
            "K_ga": self.k_ga.tolist(),
        }

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> GSensitivityStep:
        return cls(type=entry["type"], sensor=entry["sensor"], k_ga=np.array(entry["K_ga"]))
