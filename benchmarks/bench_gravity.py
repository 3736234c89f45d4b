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
(c) ``RateCheck``, the gyroscope against the accelerometer's turning, on real recordings (the
    three ROS 1 bags of imu_tools' ``imu_filter_madgwick/sample``, from
    ``scripts/fetch_public_recordings.py``; absent ones are skipped) and on this course (with no
    gyroscope bias and with 5 °/s, not learnt yet at the start): the share it ends on,
    whether it agrees, how often the verdict changed, when it first judged, and what it names;
    the rates as recorded, in deg/s (times 180/pi) and negated.

``--ramp S``: (a) and (b) with every change of speed and turn rate eased in over S seconds (a
raised cosine, commanded at 100 Hz, as a smooth controller or a joystick pushed gradually
does): the acceleration then builds up instead of stepping.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_gravity.py            # seeds 1 2 3
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_gravity.py --ramp 2
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
from mag_calibrator_ros.calibration.live.pairing import force_problem  # noqa: E402
from mag_calibrator_ros.calibration.live.session import CalibrationSession  # noqa: E402
from mag_calibrator_ros.sim import motion  # noqa: E402
from mag_calibrator_ros.sim.board import BoardModel, course_recording  # noqa: E402
from mag_calibrator_ros.tools.demo import GROUND_HARD_IRON_UT, azimuth_errors_deg  # noqa: E402
from mag_calibrator_ros.tools.recordings import read_recording  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'scripts'))
from fetch_public_recordings import recordings_dir  # noqa: E402

COURSE = motion.GROUND_COURSE[:7]
BIASED_DPS = (2.0, -2.0, 1.0)
LARGEST_BIAS_DPS = (5.0, -5.0, 1.0)
"""The ICM-20948's zero-rate tolerance, ±5 °/s an axis (DS-000189 table 1)."""


class AccelerometerAsGravity(GravityTracker):
    """What every reading was levelled by before the tracker: the specific force's direction."""

    def update(self, stamp_ns, force, gyro, frame_id=''):
        return super().update(stamp_ns, force, None, frame_id)


class EasedCourse(motion.CourseDriver):
    """The course's commands eased from one leg's to the next over ``ramp_s`` (raised cosine)."""

    def __init__(self, legs: tuple[motion.Leg, ...], ramp_s: float) -> None:
        super().__init__(legs)
        self.ramp_s = ramp_s
        self.leg_ends = np.cumsum([leg.duration_s for leg in legs])

    def command_at(self, t: float) -> tuple[float, float]:
        now = super().command_at(t)
        index = int(np.searchsorted(self.leg_ends, t, side='right'))
        if index == 0 or self.ramp_s <= 0.0:
            return now
        since = t - self.leg_ends[index - 1]
        before = super().command_at(self.leg_ends[index - 1] - 1e-9)
        share = 0.5 - 0.5 * math.cos(math.pi * min(1.0, since / self.ramp_s))
        return tuple(b + share * (n - b) for b, n in zip(before, now, strict=True))


def course(ramp_s: float) -> tuple[motion.CourseDriver, float]:
    """The driven course and how often its commands are sent (s)."""
    if ramp_s > min(leg.duration_s for leg in COURSE):
        raise SystemExit('--ramp must not exceed the shortest leg (each eases from the last)')
    if ramp_s > 0.0:
        return EasedCourse(COURSE, ramp_s), 0.01
    return motion.CourseDriver(COURSE), 0.1


def board(seed: int, gyro_bias_dps=(0.0, 0.0, 0.0), noise_ut: float = 0.3) -> BoardModel:
    plain = robot(seed, interference=False, noise_ut=noise_ut)
    return BoardModel(replace(plain.config, gyro_bias_dps=gyro_bias_dps), plain.trajectory)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, cosine)))


def directions(seed: int, gyro_bias_dps, ramp_s: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a): per-sample errors of the accelerometer and of the tracker (NaN: none given), and the
    bias it learnt (°/s). The truth is read while the course is driven (commands change the
    trajectory's future only)."""
    simulated = board(seed, gyro_bias_dps)
    trajectory = simulated.trajectory
    driver, period = course(ramp_s)
    tracker = GravityTracker()
    measured, tracked = [], []
    next_command = 0.0
    for k in range(int(round(driver.duration_s * RATE_HZ))):
        t = k / RATE_HZ
        while next_command <= t:
            speed, yaw_rate = driver.command_at(next_command)
            trajectory.command(yaw_rate, next_command, speed=speed)
            next_command += period
        accel, gyro, truth = simulated.inertial(t, 57.0, 57.0)
        up = truth.rotation.T @ (0.0, 0.0, 1.0)
        measured.append(angle_deg(accel, up))
        given = tracker.update(round(t * 1e9), tuple(accel), tuple(gyro), 'imu_link')
        tracked.append(math.nan if given is None else angle_deg(np.asarray(given), up))
    return np.array(measured), np.array(tracked), np.degrees(tracker.bias)


def calibrate(seed: int, tracked: bool, ramp_s: float = 0.0) -> tuple[str, np.ndarray, float]:
    """(b): the answer, its offset (uT) and its heading RMS over a noise-free full turn."""
    driver, period = course(ramp_s)
    recording = course_recording(board(seed), driver, rate_hz=RATE_HZ, command_period_s=period)
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


def rate_check(stamps_ns: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> str:
    """(c): one tracker over the rows; what its RateCheck ends on."""
    tracker = GravityTracker()
    changes, first, verdict = 0, None, True
    for stamp, force, rate in zip(stamps_ns.tolist(), accel.tolist(), gyro.tolist(),
                                  strict=True):
        if force_problem(tuple(force), None) or not np.all(np.isfinite(rate)):
            continue
        tracker.update(int(stamp), tuple(force), tuple(rate))
        check = tracker.rates
        if first is None and check.scale is not None:
            first = (stamp - stamps_ns[0]) * 1e-9
        changes += check.agree != verdict
        verdict = check.agree
    check = tracker.rates
    if check.scale is None:
        return 'not judged (too little tilting)'
    named = ('deg/s named' if check.looks_like_degrees
             else 'axes or unit asked' if check.problem() else '')
    return (f'share {check.scale:+.3f}, {"agrees" if check.agree else "disagrees"}'
            f' (verdict changed {changes}x, first judged at {first:.1f} s) {named}')


def rate_checks(seeds: list[int]) -> None:
    sources = []
    for name in ('sparkfun_razor.bag', 'ardrone_imu.bag', 'phidgets_imu_upside_down.bag'):
        path = recordings_dir() / name
        if not path.exists():
            print(f'  {name}: absent (scripts/fetch_public_recordings.py)')
            continue
        recording = read_recording(path, accel_topic='')
        stamps = np.round(recording.stamps * 1e9).astype(np.int64)
        sources.append((name, stamps, recording.accel, recording.gyro))
    for seed in seeds:
        for bias in ((0.0, 0.0, 0.0), LARGEST_BIAS_DPS):
            recording = course_recording(board(seed, bias), motion.CourseDriver(COURSE),
                                         rate_hz=RATE_HZ)
            stamps = np.round(recording.times * 1e9).astype(np.int64)
            sources.append((f'this course, seed {seed}, gyroscope bias {bias} °/s', stamps,
                            recording.accel, recording.gyro))
    for name, stamps, accel, gyro in sources:
        for what, rates in (('as recorded', gyro), ('deg/s', np.degrees(gyro)),
                            ('negated', -gyro)):
            print(f'  {name}, {what}: {rate_check(stamps, accel, rates)}')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    parser.add_argument('--ramp', type=float, default=0.0,
                        help='ease every command change over this many seconds')
    args = parser.parse_args(argv)
    print('(a) angle to the true gravity (deg): RMS / p99 / worst; share given; bias learnt')
    for bias in ((0.0, 0.0, 0.0), BIASED_DPS):
        for seed in args.seeds:
            measured, tracked, learnt = directions(seed, bias, args.ramp)
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
            message, offset, heading = calibrate(seed, tracked, args.ramp)
            dip = re.search(r'dip ([0-9.]+) deg', message)
            residual = re.search(r'residual ([0-9.]+) %', message)
            what = 'tracker      ' if tracked else 'accelerometer'
            error = offset[:2] - truth[:2]
            print(f'  seed {seed} {what}: {error[0]:+.2f}, {error[1]:+.2f};'
                  f' z {offset[2]:.1f}; dip {dip.group(1) if dip else "held"};'
                  f' residual {residual.group(1) if residual else "?"} %;'
                  f' heading {heading:.2f}° RMS')
    print("(c) the gyroscope against the accelerometer's turning (RateCheck)")
    rate_checks(args.seeds)
    return 0


if __name__ == '__main__':
    sys.exit(main())
