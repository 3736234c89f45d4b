# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The live input watched for mistakes no calibration can fix (``fit/input_sanity.py``).

``InputWatch`` sees every magnetometer message before screening (a field in gauss published as
tesla is refused by screening as saturated, so screening alone would only count it) and every
accelerometer sample, O(1) each; it judges a small window of fields at the fifth message and then
once a second of stream time, and the accelerometer's latest second, so a wrong unit is said
within a second of data and a normalised field within a few seconds of turning. While a
problem stands, no fit runs that could put a
calibration in force (``refusal``); the session logs each new problem once and /diagnostics
shows it as a WARN.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.input_sanity import (
    MIN_READINGS,
    NORMALISED_SPREAD,
    accel_unit_problem,
    field_unit_problem,
    magnitude_spread,
    normalised_problem,
)

WINDOW = 200
"""Latest magnetometer messages judged (2 s at 100 Hz; all of a slow stream's last minutes)."""

JUDGE_PERIOD_S = 1.0
"""Stream seconds between judgements after the first."""

IMU_SPAN_S = 1.0
"""Accelerometer samples are judged on the median |a| of the latest second of stream: a hand's
motion moves a shorter median by far more than gravity (BROAD's trial 28: 1.2 m/s^2 over
0.175 s, 6.3 over a second), and the factor of a wrong unit (g: 9.8) is not moved by a second of
motion that goes nowhere."""

IMU_JUDGE_EVERY = 100
"""...judged once the samples span IMU_SPAN_S, then every IMU_JUDGE_EVERY samples."""

NORMALISED = 'the magnetometer input is already normalised'

FITS_REFUSED = ('calibrate', 'refine', 'request', 'gyro')
"""The fits whose outcome could go in force; reference fits and checks change nothing."""


class InputWatch:
    """Wrong units and normalised fields in the input, said once each, refused while they last.

    ``tesla``: the stream claims tesla (the node; ``mag_calibrator_fit`` on a bag). A recording
    in its own unit (µT, counts) is only judged for normalisation.
    """

    def __init__(self, tesla: bool = True, full_scale: float | None = None) -> None:
        self.tesla = tesla
        self.full_scale = full_scale
        """The magnetometer's full scale (T): fields up to it can be tesla (the unit check)."""
        self._fields: deque[tuple[float, float, float]] = deque(maxlen=WINDOW)
        self._accel: deque[tuple[int, tuple[float, float, float]]] = deque()
        self._offered = 0
        self._imu_offered = 0
        self._imu_judged = 0
        self._next_judgement: float | None = None
        self.problem = ''
        """What is wrong with the magnetometer input now ('' when nothing)."""
        self.imu_problem = ''
        """What is wrong with the accelerometer input now ('' when nothing)."""
        self._new: list[str] = []

    def offer(self, stamp_ns: int, field: Sequence[float]) -> list[str]:
        """One magnetometer message (any values: non-finite ones are left out of judgements);
        returns the problems found since the last call (this one's or an IMU sample's), each
        once, for the session to log."""
        if all(math.isfinite(value) for value in field):
            self._judge(stamp_ns, field)
        return self.take_new() if self._new else []

    def _judge(self, stamp_ns: int, field: Sequence[float]) -> None:
        self._fields.append((field[0], field[1], field[2]))
        self._offered += 1
        now = stamp_ns * 1e-9
        due = self._next_judgement
        if self._offered == MIN_READINGS or (due is not None and not now < due):
            self._next_judgement = now + JUDGE_PERIOD_S
            rows = np.array(self._fields)
            problem = (field_unit_problem(rows, full_scale_t=self.full_scale) if self.tesla
                       else None) or normalised_problem(rows)
            if problem is None and self.problem.startswith(NORMALISED):
                # a still spell leaves the magnitude as constant: only a varying one clears it
                problem = self.problem if magnitude_spread(rows) <= NORMALISED_SPREAD else None
            self._change('problem', problem or '')
        elif due is not None and now < due - 10.0 * JUDGE_PERIOD_S:
            self._next_judgement = now  # stamps went back (a replay): judge from now on

    def offer_imu(self, stamp_ns: int, accel: Sequence[float]) -> None:
        """One accelerometer sample, m/s^2 as sensor_msgs/Imu requires; O(1) but one judgement
        every IMU_JUDGE_EVERY."""
        try:
            row = tuple(float(value) for value in accel)
        except (TypeError, ValueError):
            return
        if len(row) != 3 or not all(math.isfinite(value) for value in row):
            return
        window = self._accel
        if window and not 0 <= stamp_ns - window[-1][0] <= IMU_SPAN_S * 1e9:
            window.clear()  # stamps went back or jumped: a new stream
        window.append((stamp_ns, row))
        while stamp_ns - window[0][0] > IMU_SPAN_S * 1e9:
            window.popleft()
        self._imu_offered += 1
        count = len(window)  # n samples stand for n sample periods of stream
        spans = count > 1 and (stamp_ns - window[0][0]) * count / (count - 1) >= IMU_SPAN_S * 1e9
        judged = self._imu_judged
        if spans and (not judged or self._imu_offered - judged >= IMU_JUDGE_EVERY):
            self._imu_judged = self._imu_offered
            rows = np.array([sample for _, sample in window])
            self._change('imu_problem', accel_unit_problem(rows) or '')

    def _change(self, which: str, problem: str) -> None:
        if problem and problem.split(':')[0] != getattr(self, which).split(':')[0]:
            self._new.append(problem)
        setattr(self, which, problem)

    def take_new(self) -> list[str]:
        """Problems found since the last call, each once (the session logs them)."""
        new, self._new = self._new, []
        return new

    def values(self) -> dict[str, str]:
        """For /diagnostics: what is wrong with the input, when something is."""
        problem = '; '.join(text for text in (self.problem, self.imu_problem) if text)
        return {'input_problem': problem} if problem else {}

    def refusal(self, kind: str) -> str | None:
        """Why a fit of this kind must not run now (its result could go in force), or None."""
        return self.problem if self.problem and kind in FITS_REFUSED else None

    def clear(self) -> None:
        """Forget the stream (``~/reset``: another sensor may follow)."""
        self.__init__(self.tesla)


__all__ = ['FITS_REFUSED', 'IMU_SPAN_S', 'JUDGE_PERIOD_S', 'WINDOW', 'InputWatch']
