# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""A session driven from recorded rows instead of live messages (``mag_calibrator_fit``, tests,
benchmarks): streaming rows through its face and asking for a fit and waiting for it.

Both use only the session's public face, so what they show is what the node would do with the
same stamps."""

from __future__ import annotations

import time

import numpy as np

from mag_calibrator_ros.calibration.live.report import CalibrationAttempt
from mag_calibrator_ros.calibration.live.session import CalibrationSession, SessionEvent


def feed(session: CalibrationSession, samples: np.ndarray, rate_hz: float = 100.0,
         start_ns: int = 0, frame_id: str = '', accel: np.ndarray | None = None,
         gyro: np.ndarray | None = None) -> None:
    """Stream recorded rows through ``process`` stamped at ``rate_hz``; ``accel`` (and
    ``gyro``, rad/s) rows go through ``process_imu`` first with the same stamps."""
    step = 1e9 / rate_hz
    accel_rows = None if accel is None else np.asarray(accel, dtype=float).tolist()
    gyro_rows = None if gyro is None else np.asarray(gyro, dtype=float).tolist()
    for index, row in enumerate(np.asarray(samples, dtype=float).tolist()):
        stamp = start_ns + round(index * step)
        if accel_rows is not None:
            session.process_imu(stamp, frame_id, accel_rows[index],
                                None if gyro_rows is None else gyro_rows[index])
        session.process(stamp, frame_id, row)


def calibrate_now(session: CalibrationSession, timeout_s: float = 60.0,
                  events: list[SessionEvent] | None = None,
                  pause_s: float = 0.001) -> CalibrationAttempt:
    """Request a fit of the buffer (``~/calibrate``) and wait for its answer. The session's
    events taken while waiting, the answer's included, are appended to ``events`` when given
    (else dropped: offline callers read the attempt). ``pause_s`` between polls lets a worker
    process run; 0 for a runner that answers after a number of polls, not of seconds."""
    ticket = session.request_calibration()
    deadline = time.monotonic() + timeout_s
    while True:
        taken = session.take_events()
        if events is not None:
            events.extend(taken)
        for event in taken:
            if event.ticket == ticket and event.attempt is not None:
                return event.attempt
        if time.monotonic() > deadline:
            return CalibrationAttempt(False, f'calibration did not finish in {timeout_s} s')
        time.sleep(pause_s)
        session.poll()
