#!/usr/bin/env python3
"""Gravity's direction on a driven ground robot, and the levelled planar fit made with it.

The robot of bench_interference without its own field (50 uT at 60° inclination, hard iron
(55, -45, 25) uT, strong soft iron, 2° of wobble that follows the heading, noise 0.3 uT,
100 Hz), driven over the first seven legs of ``motion.GROUND_COURSE`` (a turn in place, 15 s
straight at 0.5 m/s, a half turn, 14 s at 0.25 m/s; starts and stops at 1 m/s^2), offline
through ``CalibrationSession`` (inline fits: the numbers do not depend on load).

(a) Per IMU sample, the angle between gravity's true direction in the chip frame and (i) the
    accelerometer's own direction, (ii) ``GravityTracker``'s (where it gives one): RMS, 99th
    percentile and worst, the share given, and the gyroscope bias it learnt; without and with a
    gyroscope bias of (2, -2, 1) °/s.
(b) ``~/calibrate`` after the course (``calibrate_now``): the in-plane offset's error, the offset
    along the turning axis (truth 25 uT; held at the data's mean when not determined), the dip
    it reports (truth 60°) and the heading RMS of its calibration over a noise-free full turn;
    gravity from the tracker (today) against the accelerometer's own direction (before).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_gravity.py            # seeds 1 2 3
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import math
from pathlib import Path
import re
import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_interference import RATE_HZ, robot  # noqa: E402  (one robot for both benchmarks)

from mag_calibrator_ros.calibration.live.gravity import GravityTracker  # noqa: E402
from mag_calibrator_ros.calibration.live.session import CalibrationSession  # noqa: E402
from mag_calibrator_ros.sim import motion  # noqa: E402
from mag_calibrator_ros.sim.board import BoardModel, course_recording  # noqa: E402
from mag_calibrator_ros.tools.demo import GROUND_HARD_IRON_UT, azimuth_errors_deg  # noqa: E402

COURSE = motion.GROUND_COURSE[:7]
BIASED_DPS = (2.0, -2.0, 1.0)


class AccelerometerAsGravity(GravityTracker):
    """What every reading was levelled by before the tracker: the specific force's direction."""

    def update(self, stamp_ns, force, gyro, frame_id=''):
        return super().update(stamp_ns, force, None, frame_id)


def board(seed: int, gyro_bias_dps=(0.0, 0.0, 0.0), noise_ut: float = 0.3) -> BoardModel:
    plain = robot(seed, interference=False, noise_ut=noise_ut)
    return BoardModel(replace(plain.config, gyro_bias_dps=gyro_bias_dps), plain.trajectory)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, cosine)))


def directions(seed: int, gyro_bias_dps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a): per-sample errors of the accelerometer and of the tracker (NaN: none given), and the
    bias it learnt (°/s). The truth is read while the course is driven (commands change the
    trajectory's future only)."""
    simulated = board(seed, gyro_bias_dps)
    trajectory = simulated.trajectory
    driver = motion.CourseDriver(COURSE)
    tracker = GravityTracker()
    measured, tracked = [], []
    next_command = 0.0
    for k in range(int(round(driver.duration_s * RATE_HZ))):
        t = k / RATE_HZ
        while next_command <= t:
            speed, yaw_rate = driver.command_at(next_command)
            trajectory.command(yaw_rate, next_command, speed=speed)
            next_command += 0.1
        accel, gyro, truth = simulated.inertial(t, 57.0, 57.0)
        up = truth.rotation.T @ (0.0, 0.0, 1.0)
        measured.append(angle_deg(accel, up))
        given = tracker.update(round(t * 1e9), tuple(accel), tuple(gyro), 'imu_link')
        tracked.append(math.nan if given is None else angle_deg(np.asarray(given), up))
    return np.array(measured), np.array(tracked), np.degrees(tracker.bias)


def calibrate(seed: int, tracked: bool) -> tuple[str, np.ndarray, float]:
    """(b): the answer, its offset (uT) and its heading RMS over a noise-free full turn."""
    recording = course_recording(board(seed), motion.CourseDriver(COURSE), rate_hz=RATE_HZ)
    session = CalibrationSession()
    if not tracked:
        session.pairing.gravity = AccelerometerAsGravity()
    session.feed(recording.mag, RATE_HZ, frame_id='imu_link', accel=recording.accel,
                 gyro=recording.gyro)
    attempt = session.calibrate_now()
    calibration = session.calibration
    session.close()
    turn = course_recording(board(seed, noise_ut=0.0), motion.CourseDriver(COURSE[:2]),
                            rate_hz=RATE_HZ)
    moving = turn.times >= COURSE[0].duration_s
    errors = azimuth_errors_deg(calibration.apply(turn.mag[moving]), turn.truth[moving])
    return attempt.message, calibration.offset * 1e6, float(np.sqrt(np.mean(errors**2)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    args = parser.parse_args(argv)
    print('(a) angle to the true gravity (deg): RMS / p99 / worst; share given; bias learnt')
    for bias in ((0.0, 0.0, 0.0), BIASED_DPS):
        for seed in args.seeds:
            measured, tracked, learnt = directions(seed, bias)
            given = np.isfinite(tracked)
            print(f'  bias {bias} seed {seed}: accelerometer {np.sqrt(np.mean(measured**2)):.3f}'
                  f' / {np.percentile(measured, 99):.2f} / {measured.max():.2f};'
                  f' tracker {np.sqrt(np.mean(tracked[given]**2)):.3f}'
                  f' / {np.percentile(tracked[given], 99):.2f} / {tracked[given].max():.2f};'
                  f' given {100 * given.mean():.1f} %; bias learnt {np.round(learnt, 2)} °/s')
    print('(b) ~/calibrate after the course: offset error x, y (uT), z offset (truth 25), dip'
          ' (truth 60), residual, heading RMS')
    truth = np.asarray(GROUND_HARD_IRON_UT, dtype=float)
    for seed in args.seeds:
        for tracked in (False, True):
            message, offset, heading = calibrate(seed, tracked)
            dip = re.search(r'dip ([0-9.]+) deg', message)
            residual = re.search(r'residual ([0-9.]+) %', message)
            what = 'tracker      ' if tracked else 'accelerometer'
            error = offset[:2] - truth[:2]
            print(f'  seed {seed} {what}: {error[0]:+.2f}, {error[1]:+.2f};'
                  f' z {offset[2]:.1f}; dip {dip.group(1) if dip else "held"};'
                  f' residual {residual.group(1) if residual else "?"} %;'
                  f' heading {heading:.2f}° RMS')
    return 0


if __name__ == '__main__':
    sys.exit(main())
