# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Pair each reading's stamp with the nearest IMU or side-topic sample, within a tolerance."""

from __future__ import annotations

import math

import numpy as np

from mag_calibrator_ros.calibration.live.pairing import PAIR_TOLERANCE_NS


def pair_by_stamp(stamps: np.ndarray, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(accel, gyro, paired): for each stamp (s), the (stamp, accel (3), gyro (3)) ``imu`` row
    nearest it within PAIR_TOLERANCE_NS, NaN rows where none is; as the node's ImuPairing does
    message by message."""
    accel = np.full((len(stamps), 3), math.nan)
    gyro = np.full((len(stamps), 3), math.nan)
    if len(imu) == 0 or len(stamps) == 0:
        return accel, gyro, 0
    imu = imu[np.argsort(imu[:, 0], kind='stable')]
    after = np.clip(np.searchsorted(imu[:, 0], stamps), 1, len(imu) - 1)
    before = after - 1
    if len(imu) == 1:
        nearest = np.zeros(len(stamps), dtype=int)
    else:
        nearest = np.where(np.abs(imu[after, 0] - stamps) < np.abs(stamps - imu[before, 0]),
                           after, before)
    close = np.abs(imu[nearest, 0] - stamps) <= PAIR_TOLERANCE_NS * 1e-9
    accel[close] = imu[nearest[close], 1:4]
    gyro[close] = imu[nearest[close], 4:7]
    return accel, gyro, int(np.count_nonzero(close))


def _nearest(stamps: np.ndarray, times: np.ndarray, values: np.ndarray, tolerance_s: float
             ) -> np.ndarray:
    """For each stamp the value of the sample nearest it within the tolerance, else NaN."""
    out = np.full(len(stamps), math.nan)
    if len(times) == 0 or len(stamps) == 0:
        return out
    order = np.argsort(times, kind='stable')
    times, values = times[order], values[order]
    after = np.clip(np.searchsorted(times, stamps), 0, len(times) - 1)
    before = np.clip(after - 1, 0, len(times) - 1)
    nearest = np.where(np.abs(times[after] - stamps) < np.abs(stamps - times[before]),
                       after, before)
    close = np.abs(times[nearest] - stamps) <= tolerance_s
    out[close] = values[nearest[close]]
    return out
