#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The live session's decisions, as a text log to compare before and after a change.

Every shared recording (three passes at 100 Hz), a synthetic tumble (plain, with online tracking,
and started from another board's calibration), a robot turning in place, and a simulated board
with an IMU and a location (still poses, and a tumble) stream through ``CalibrationSession``
offline (``InlineRunner``: the node's decisions on the same stamps, without its timing). Printed:
every event with the message at which it came out, the final state, adoptions and fits, the
/diagnostics values and progress text of the IMU runs, and the final calibration to 17 digits.

A refactor that claims "no behaviour change" shows an identical log::

    git stash; python benchmarks/decision_log.py --data ../shared/data > /tmp/before.txt
    git stash pop; python benchmarks/decision_log.py --data ../shared/data > /tmp/after.txt
    diff /tmp/before.txt /tmp/after.txt
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.earth_field import earth_field
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.tools.recordings import read_recording

DEFAULT_DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'
STEP_NS = 10_000_000  # 100 Hz stamps
POLL_EVERY = 50  # messages between polls, as a node's poll timer interleaves with messages

RECORDINGS = (
    ('gd-notebook long', 'gd-notebook/mag_raw_data_long.txt', None),
    ('gd-notebook short', 'gd-notebook/mag_raw_data.txt', None),
    ('gd deployment 1', 'gd-notebook/deployment/validation_data_step1en1.txt', '3,4,5'),
    ('gd deployment 2', 'gd-notebook/deployment/validation_data_step1en2.txt', '3,4,5'),
    ('gd deployment 3', 'gd-notebook/deployment/validation_data_step1en3.txt', '3,4,5'),
    ('fxos8700', 'fxos8700-mwrona/mag-readings.txt', None),
    ('bno055', 'bno055-jremington/bno055_mag.csv', None),
    ('lsm303dlhc', 'lsm303dlhc-altimu10v3/mag_2.txt', None),
    ('lsm303dlhc log', 'lsm303dlhc-altimu10v3/cal_output_2.log', '3,4,5'),
)
SOFT_IRON = np.array([[1.1, 0.05, 0.0], [0.05, 0.93, 0.02], [0.0, 0.02, 1.0]])
HARD_IRON_T = np.array([30e-6, -20e-6, 10e-6])


def _print_events(session: CalibrationSession, index: int) -> None:
    for event in session.take_events():
        print(f'  {index} {event.level} adopted={event.adopted} {event.message}')


def _print_calibration(calibration: Calibration | None) -> None:
    if calibration is None:
        return
    for name, values in (('offset', calibration.offset), ('matrix', calibration.matrix.ravel()),
                         ('rotation', calibration.rotation.ravel())):
        print(f'  {name}', np.array2string(values, precision=17))


def stream(name: str, rows: np.ndarray, passes: int = 3, calibration: Calibration | None = None,
           **settings: object) -> None:
    """Rows through a session with the saturation check off (the recordings are in µT or
    counts: the engine is unit-free)."""
    session = CalibrationSession(SessionSettings(full_scale=0.0, **settings), calibration,
                                 metadata={'units': 'input'})  # not tesla: as the CLI says
    print(f'== {name} ({len(rows)} rows x {passes}, {settings})')
    index = 0
    for _ in range(passes):
        for row in rows:
            session.process(index * STEP_NS, 'mag', row)
            index += 1
            if index % POLL_EVERY == 0:
                session.poll()
            _print_events(session, index)
    final = session.report(measure_coverage=True)
    print(f'  final state {final.state}; adoptions {sorted(final.counts.adoptions.items())}; '
          f'jobs {sorted(final.counts.fits.items())}')
    _print_calibration(session.calibration)
    session.close()


def board_stream(kind: str, seconds: float = 60.0, rate_hz: float = 50.0) -> None:
    """A simulated board with its accelerometer and gyroscope, at a location (the World
    Magnetic Model's field), the magnetometer misaligned: pairing, alignment, the model's check."""
    config = SimConfig(motion=kind, hard_iron_ut=(20.0, -10.0, 5.0), seed=4,
                       mag_misalignment_deg=(3.0, -2.0, 1.0), latitude=52.0, longitude=4.0)
    mag, accel, gyro = board_readings(BoardModel(config), seconds, rate_hz)
    session = CalibrationSession(SessionSettings())
    session.set_earth_field(earth_field(52.0, 4.0, 0.0))
    print(f'== imu {kind} ({len(mag)} rows)')
    step = round(1e9 / rate_hz)
    for index in range(len(mag)):
        session.process_imu(index * step, 'imu', accel[index], gyro[index])
        session.process(index * step, 'imu', mag[index])
        if index % POLL_EVERY == 0:
            session.poll()
        _print_events(session, index)
    final = session.report(0.0, measure_coverage=True)
    print(f'  final state {final.state}; adoptions {sorted(final.counts.adoptions.items())}')
    print('  diagnostics', sorted((k, v) for k, v in final.values.items() if 'rate' not in k))
    print('  progress', final.progress)
    _print_calibration(session.calibration)
    session.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', type=Path, default=DEFAULT_DATA,
                        help='the shared recordings (default: ../shared/data)')
    args = parser.parse_args(argv)
    for name, path, columns in RECORDINGS:
        stream(name, read_recording(args.data / path, columns=columns).samples)
    rng = np.random.default_rng(3)
    tumble = motion.body_field_samples('tumble', 3000, 100.0, 50e-6, 60.0, seed=1)
    raw = tumble @ SOFT_IRON.T + HARD_IRON_T + rng.normal(0, 0.3e-6, tumble.shape)
    stream('tumble', raw, passes=2)
    stream('tumble tracking', raw, passes=2, online_tracking=True)
    wrong = Calibration(np.array([-30e-6, 40e-6, 5e-6]), np.eye(3), 50e-6)
    stream('tumble wrong file', raw, passes=2, calibration=wrong)
    yaw = motion.body_field_samples('yaw', 3000, 100.0, 50e-6, 60.0, seed=2)
    stream('yaw', yaw @ SOFT_IRON.T + HARD_IRON_T + rng.normal(0, 0.3e-6, yaw.shape), passes=1)
    for kind in ('poses', 'tumble'):
        board_stream(kind)
    return 0


if __name__ == '__main__':
    sys.exit(main())
