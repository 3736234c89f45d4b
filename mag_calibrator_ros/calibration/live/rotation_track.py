# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The gyroscope's turning, integrated between messages, and the readings it turned: what the
gyro-aided fit (``fit/gyro_aided.py``) learns the hard iron from without a sphere.

The attitude is the gyroscope's rates integrated (quaternions, plain floats: a few microseconds
an IMU sample on the message path) from the start of each unbroken stream of rates; a reading
takes the attitude at its stamp (the last rate carried over the few milliseconds between). The
readings kept are thinned to one per STEP_S and grouped in windows of WINDOW_S of one stream:
within a window the gyroscope's bias turns the field by little (0.5 deg/s over half a second is
a quarter of a degree), and each window has a frame of its own.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from itertools import takewhile
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.gyro_aided import TurnedReadings
from mag_calibrator_ros.calibration.live.jobs import WINDOWS_NEEDED

STEP_S = 0.02
"""One reading kept per 20 ms of stream (50 Hz): more add noise samples, not turning."""

WINDOW_S = 0.5
"""A window of readings shares one frame: half a second of integrated rates."""

SPAN_S = 2.0
"""Windows of one stream are grouped in spans of 2 s, what a refinement's directions are judged
over (``turned_direction_errors``): a hand turns tens of degrees in them, enough for a bent
direction to show, while a gyroscope's bias (well under 0.5 deg/s) turns the field by less than
a degree."""

MAX_GAP_S = 0.1
"""Rates further apart than this (or going back) start a new stream: a turn in the gap is
unknown."""

MAX_READINGS = 6000
"""Readings kept: the last two minutes at 50 Hz. Each window stands alone (its own frame), so
old windows judge a refinement as well as new ones: a soft iron fitted to the sphere's latest
directions that bends the earlier ones is refused (BROAD trial 04: worse by 12 % on the
minute before it, not on the last 30 s)."""

FIT_PERIOD_S = 2.0
"""Stream seconds between gyro-aided fits while nothing is in force."""

FIT_WINDOWS = 60
"""The first calibration fits the latest 60 windows (30 s): the more turning, the surer the
offset; a magnet attached meanwhile is a step the next looks find."""

STEP_WINDOWS = 12
"""A hard-iron step is looked for in the latest 12 windows (6 s) once calibrated."""

STEP_PERIOD_S = 1.0
"""Stream seconds between looks for a step."""

Quaternion = tuple[float, float, float, float]


class RotationTrack:
    """Integrates the gyroscope (rad/s) and keeps recent readings with their attitudes."""

    def __init__(self) -> None:
        self._readings: deque[tuple[int, int, tuple[float, float, float], list]] = deque(
            maxlen=MAX_READINGS)
        self.reset()

    def reset(self) -> None:
        """Forget the readings and the stream (a reset, another sensor)."""
        self.forget()
        self._stream = 0  # bumped by each new stream of rates
        self._attitude: Quaternion = (1.0, 0.0, 0.0, 0.0)
        self._rate: tuple[float, float, float] | None = None
        self._rate_stamp: int | None = None
        self._next_fit_s = 0.0
        self._next_refit_s = 0.0

    def forget(self) -> None:
        """Forget the readings kept (the sensor changed), not the turning integrated."""
        self._readings.clear()
        self._kept_stamp: int | None = None
        self._window = self._span = -1
        self._window_start: int | None = None
        self._span_start: int | None = None
        self._window_stream = -1

    def add_rate(self, stamp_ns: int, rate: Sequence[float]) -> None:
        """One gyroscope sample; O(1)."""
        try:
            wx, wy, wz = (float(value) for value in rate)
        except (TypeError, ValueError):
            return
        if not (math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz)):
            self._rate = None
            return
        last = self._rate_stamp
        if self._rate is None or last is None or not 0 < stamp_ns - last <= MAX_GAP_S * 1e9:
            self._stream += 1
            self._attitude = (1.0, 0.0, 0.0, 0.0)
        else:
            dt = (stamp_ns - last) * 1e-9
            px, py, pz = self._rate  # trapezoid: the mean of the two rates over the step
            self._attitude = _turned(self._attitude, 0.5 * (px + wx) * dt, 0.5 * (py + wy) * dt,
                                     0.5 * (pz + wz) * dt)
        self._rate, self._rate_stamp = (wx, wy, wz), stamp_ns

    def add_reading(self, stamp_ns: int, reading: Sequence[float]) -> None:
        """One accepted reading (the own field removed); kept one per STEP_S with the attitude
        at its stamp when the rates reach it."""
        last = self._rate_stamp
        if self._rate is None or last is None or abs(stamp_ns - last) > MAX_GAP_S * 1e9:
            return
        if self._kept_stamp is not None and 0 <= stamp_ns - self._kept_stamp < STEP_S * 1e9:
            return
        dt = (stamp_ns - last) * 1e-9
        wx, wy, wz = self._rate
        attitude = _turned(self._attitude, wx * dt, wy * dt, wz * dt)
        if (self._window_stream != self._stream or self._window_start is None
                or not 0 <= stamp_ns - self._window_start < WINDOW_S * 1e9):
            if (self._window_stream != self._stream or self._span_start is None
                    or not 0 <= stamp_ns - self._span_start < SPAN_S * 1e9):
                self._span, self._span_start = self._span + 1, stamp_ns
            self._window += 1
            self._window_start, self._window_stream = stamp_ns, self._stream
        self._kept_stamp = stamp_ns
        self._readings.append((self._window, self._span, tuple(float(v) for v in reading),
                               _matrix(attitude)))  # once here, not at every snapshot

    def due(self, now_s: float, period_s: float = FIT_PERIOD_S,
            windows: int = WINDOWS_NEEDED) -> bool:
        """Whether a gyro-aided fit is due: every ``period_s`` once ``windows`` are kept."""
        if now_s < self._next_fit_s or not self._enough(windows):
            return False
        self._next_fit_s = now_s + period_s
        return True

    def fit_due(self, now_s: float, calibrated: bool, improvable: bool = False) -> str | None:
        """The gyro-aided fit due now: 'gyro' while nothing is in force, and every FIT_PERIOD_S
        while a gyro fit in force may be improved on (``improvable``); once calibrated 'step'
        every STEP_PERIOD_S (a magnet attached: the offset steps); None when none is."""
        if not calibrated:
            return 'gyro' if self.due(now_s) else None
        if improvable and now_s >= self._next_refit_s and self._enough():
            self._next_refit_s = now_s + FIT_PERIOD_S
            return 'gyro'
        return 'step' if self.due(now_s, STEP_PERIOD_S, STEP_WINDOWS) else None

    def fit_snapshot(self, kind: str) -> TurnedReadings | None:
        """The readings a 'gyro' (FIT_WINDOWS) or 'step' (STEP_WINDOWS) fit takes."""
        return self.snapshot(FIT_WINDOWS if kind == 'gyro' else STEP_WINDOWS)

    def snapshot(self, last_windows: int | None = None) -> TurnedReadings | None:
        """The readings kept (of the latest ``last_windows`` windows: None, all), their
        attitudes (as rotation matrices), windows and spans; None before WINDOWS_NEEDED are
        kept."""
        if not self._enough(min(WINDOWS_NEEDED, last_windows or WINDOWS_NEEDED)):
            return None
        kept = self._readings
        if last_windows is not None:  # from the newest back: O(what is taken), not O(kept)
            first = kept[-1][0] - last_windows + 1
            kept = list(takewhile(lambda item: item[0] >= first, reversed(kept)))[::-1]
        windows = np.array([item[0] for item in kept], dtype=int)
        spans = np.array([item[1] for item in kept], dtype=int)
        readings = np.array([item[2] for item in kept], dtype=float)
        rotations = np.array([item[3] for item in kept], dtype=float)
        return TurnedReadings(readings.reshape(-1, 3), rotations.reshape(-1, 3, 3),
                              windows - (windows[0] if len(windows) else 0),
                              spans - (spans[0] if len(spans) else 0))


    def _enough(self, windows: int = WINDOWS_NEEDED) -> bool:
        readings = self._readings
        return bool(readings) and readings[-1][0] - readings[0][0] + 1 >= windows


def _turned(q: Quaternion, ax: float, ay: float, az: float) -> Quaternion:
    """``q`` turned by the body-frame rotation vector (ax, ay, az): q * exp(a / 2)."""
    angle = math.sqrt(ax * ax + ay * ay + az * az)
    if angle < 1e-12:
        return q
    half = 0.5 * angle
    s = math.sin(half) / angle
    bw, bx, by, bz = math.cos(half), ax * s, ay * s, az * s
    w, x, y, z = q
    w, x, y, z = (w * bw - x * bx - y * by - z * bz, w * bx + x * bw + y * bz - z * by,
                  w * by - x * bz + y * bw + z * bx, w * bz + x * by - y * bx + z * bw)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / norm, x / norm, y / norm, z / norm)


def _matrix(q: Quaternion) -> list[list[float]]:
    w, x, y, z = q
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


__all__ = ['RotationTrack']
