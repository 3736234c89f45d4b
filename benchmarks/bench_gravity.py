#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
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
(d) The live session over the whole three-minute ``motion.GROUND_COURSE`` (straight legs and
    stops at a few headings between the turns), with its defaults: the heading RMS over a
    noise-free full turn of the first calibration it puts in force, of the last, and of the
    worst, and how many it put in force; at the magnetometer noise of each ``--noise`` (uT).
(e) The levelled fit alone (``fit_calibration``, offline, gravity's true direction) on a robot
    that turns a little over a circle on a 2° wobbly floor, stands 15 s, turns a half circle
    and stands 14 s, with no soft iron and under six random ones (symmetric, spread 0.12), on six
    floors each:
    the heading RMS over a noise-free turn of another floor, mean and worst, at each noise.

``--ramp S``: (a) and (b) with every change of speed and turn rate eased in over S seconds (a
raised cosine, commanded at 100 Hz, as a smooth controller or a joystick pushed gradually
does): the acceleration then builds up instead of stepping.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_gravity.py            # seeds 1 2 3
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_gravity.py --ramp 2
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_gravity.py --parts d --seeds 1 2 3 4 5 6 7 8
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

from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration  # noqa: E402
from mag_calibrator_ros.calibration.live.gravity import GravityTracker  # noqa: E402
from mag_calibrator_ros.calibration.live.offline import calibrate_now, feed  # noqa: E402
from mag_calibrator_ros.calibration.live.pairing import ImuPairing, force_problem  # noqa: E402
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
    session = CalibrationSession(
        pairing=None if tracked else ImuPairing(gravity=AccelerometerAsGravity()))
    feed(session, recording.mag, RATE_HZ, frame_id='imu_link', accel=recording.accel,
         gyro=recording.gyro)
    attempt = calibrate_now(session)
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


def in_force_headings(seed: int, noise_ut: float) -> list[float]:
    """(d): the heading RMS (over a noise-free full turn) of every calibration the live session
    put in force over the whole course, in order."""
    recording = course_recording(board(seed, noise_ut=noise_ut), motion.CourseDriver(),
                                 rate_hz=RATE_HZ)
    turn = course_recording(board(seed, noise_ut=0.0), motion.CourseDriver(COURSE[:2]),
                            rate_hz=RATE_HZ)
    moving = turn.times >= COURSE[0].duration_s
    session = CalibrationSession()
    headings, last = [], None
    for index, stamp in enumerate(np.round(recording.times * 1e9).astype(np.int64).tolist()):
        session.process_imu(stamp, 'imu_link', recording.accel[index], recording.gyro[index])
        session.process(stamp, 'imu_link', recording.mag[index])
        session.poll()
        if session.calibration is not None and session.calibration is not last:
            last = session.calibration
            errors = azimuth_errors_deg(last.apply(turn.mag[moving]), turn.truth[moving])
            headings.append(float(np.sqrt(np.mean(errors**2))))
    session.close()
    return headings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    parser.add_argument('--ramp', type=float, default=0.0,
                        help='ease every command change over this many seconds')
    parser.add_argument('--parts', default='abcde', help='which parts to run (default abcde)')
    parser.add_argument('--noise', type=float, nargs='+', default=[0.3, 0.6],
                        help="(d): the magnetometer's noise, uT (default 0.3 0.6)")
    args = parser.parse_args(argv)
    if 'a' in args.parts:
        part_a(args)
    if 'b' in args.parts:
        part_b(args)
    if 'c' in args.parts:
        print("(c) the gyroscope against the accelerometer's turning (RateCheck)")
        rate_checks(args.seeds)
    if 'd' in args.parts:
        part_d(args)
    if 'e' in args.parts:
        part_e(args)
    return 0


def part_a(args: argparse.Namespace) -> None:
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


def part_b(args: argparse.Namespace) -> None:
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


def part_d(args: argparse.Namespace) -> None:
    print('(d) the live session over the whole course: heading RMS of the calibrations in force'
          ' (first / last / worst, deg) and how many')
    for noise_ut in args.noise:
        rows = []
        for seed in args.seeds:
            headings = in_force_headings(seed, noise_ut)
            if not headings:
                print(f'  noise {noise_ut} uT seed {seed}: none put in force')
                continue
            rows.append((headings[0], headings[-1], max(headings)))
            print(f'  noise {noise_ut} uT seed {seed}: {headings[0]:.3f} / {headings[-1]:.3f} /'
                  f' {max(headings):.3f}, {len(headings)} in force')
        if rows:
            first, final, worst = np.array(rows).T
            print(f'  noise {noise_ut} uT over {len(rows)} seeds: first mean {first.mean():.3f}'
                  f' max {first.max():.3f}; last mean {final.mean():.3f} max {final.max():.3f};'
                  f' worst mean {worst.mean():.3f} max {worst.max():.3f}')



DWELLING = ((14.0, 0.5), (15.0, 0.0), (4.0, 0.8), (14.0, 0.0))
"""(e): (seconds, yaw rate rad/s): a turn a little over a circle, a stand, a half turn, a stand."""
E_HARD_IRON_UT = np.array([20.0, -30.0, 40.0])


def turned(seed: int, soft_iron: np.ndarray, noise_ut: float,
           legs: tuple[tuple[float, float], ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(e): (raw uT, gravity's unit direction, true field uT) in the chip frame, at 50 Hz."""
    trajectory = motion.CmdVelTrajectory(seed=seed, wobble_deg=2.0)
    earth = motion.earth_field(50.0, 60.0)
    rng = np.random.default_rng([seed, 7])
    raw, ups, truth = [], [], []
    start = 0.0
    for duration, rate in legs:
        for t in np.arange(start, start + duration, 0.02):
            trajectory.command(rate, float(t))
            rotation = trajectory.state(float(t)).rotation
            field = rotation.T @ earth
            raw.append(soft_iron @ field + E_HARD_IRON_UT + rng.normal(0.0, noise_ut, 3))
            ups.append(rotation.T @ np.array([0.0, 0.0, 1.0]))
            truth.append(field)
        start += duration
    return np.array(raw), np.array(ups), np.array(truth)


def part_e(args: argparse.Namespace) -> None:
    print('(e) the levelled fit alone, a turn and two stands: heading RMS (deg) over six floors,'
          ' mean / worst, per soft iron')
    rng = np.random.default_rng(5)
    soft_irons = [np.eye(3)]  # none: the noise is the same in every corrected axis too
    for _ in range(6):
        spread = rng.normal(0.0, 0.12, (3, 3))
        soft_irons.append(np.eye(3) + (spread + spread.T) / 2.0)
    check_raw = {}
    for noise_ut in args.noise:
        for index, soft_iron in enumerate(soft_irons):
            if index not in check_raw:
                check_raw[index] = turned(99, soft_iron, 0.0, ((2.0, 0.0), (14.0, 0.5)))
            raw_check, _, truth = check_raw[index]
            errors = []
            for floor in range(6):
                raw, ups, _ = turned(floor, soft_iron, noise_ut, DWELLING)
                result = fit_calibration(raw * 1e-6, FitOptions(model='planar'), ups=ups)
                corrected = result.calibration.apply(raw_check[100:] * 1e-6)
                errors.append(float(np.sqrt(np.mean(
                    azimuth_errors_deg(corrected, truth[100:]) ** 2))))
            eigenvalues = np.round(np.linalg.eigvalsh(soft_iron), 2)
            print(f'  noise {noise_ut} uT, soft iron {index} (eigenvalues {eigenvalues}):'
                  f' {np.mean(errors):.3f} / {np.max(errors):.3f}')


if __name__ == '__main__':
    sys.exit(main())
