# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The ICM-20948's and the AK09916's conversions between register counts and SI units.

Pure datasheet arithmetic (TDK DS-000189, AKM AK09916) on the constants in ``registers``: the
driver reads with them and the simulator writes with them, so the simulated chip follows the
datasheet rather than whatever the driver does.
"""

from __future__ import annotations

import math

import numpy as np

from mag_calibrator_ros.icm20948 import registers as reg


def counts_to_tesla(counts: np.ndarray) -> np.ndarray:
    """AK09916 counts (its own axes) -> tesla in the accel/gyro chip frame."""
    return np.asarray(counts, dtype=float) * np.asarray(reg.AXIS_SIGNS) * reg.TESLA_PER_LSB


def tesla_to_counts(field_tesla: np.ndarray) -> np.ndarray:
    """Inverse of ``counts_to_tesla`` (rounded to whole counts)."""
    chip = np.asarray(field_tesla, dtype=float) / reg.TESLA_PER_LSB
    return np.rint(chip * np.asarray(reg.AXIS_SIGNS)).astype(np.int64)


def accel_scale(range_g: int) -> float:
    """m/s^2 per LSB at the ±``range_g`` full scale."""
    return reg.STANDARD_GRAVITY / reg.ACCEL_RANGES_G[range_g][1]


def gyro_scale(range_dps: int) -> float:
    """rad/s per LSB at the ±``range_dps`` full scale."""
    return math.radians(1.0) / reg.GYRO_RANGES_DPS[range_dps][1]


def temperature_celsius(raw: int) -> float:
    """TEMP_OUT -> degC (DS-000189 TEMP_OUT_L, page not verified: (TEMP_OUT - RoomTemp_Offset)
    / 333.87 + 21; RoomTemp_Offset taken as 0)."""
    return raw / reg.TEMP_SENSITIVITY_LSB_PER_C + reg.TEMP_OFFSET_C


def temperature_counts(celsius: float) -> int:
    """Inverse of ``temperature_celsius``, rounded and saturated to int16."""
    raw = round((celsius - reg.TEMP_OFFSET_C) * reg.TEMP_SENSITIVITY_LSB_PER_C)
    return min(max(raw, reg.INT16_MIN), reg.INT16_MAX)
