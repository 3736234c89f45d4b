#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field (issue #26): heading while a ground robot drives and warms up.

The simulated ground robot of bench_ground (50 uT at 60° inclination, hard iron (55, -45, 25)
uT, strong soft iron, 2° tilt wobble that follows the heading, noise 0.3 uT, 100 Hz, the
accelerometer and gyroscope paired at the same instants) drives ``motion.GROUND_COURSE`` from
power-on: three minutes of straight legs from a crawl to its top speed (0.5 m/s) at many
headings, turns in place both ways, and stops. Its battery current (``motion.DriveCurrent``:
0.5 A idle, 5.0 A with both wheels at top speed) puts 8 uT along the chip's x axis at the full
current (K = 1.6 uT/A); its die warms by 20 °C (20 -> 40 °C, first order, time constant 60 s,
so 95 % of it within the course) and the hard iron drifts 0.2 uT/°C along y (c, T0 = 20 °C).
At a 25 uT horizontal field, 8 uT across the heading is up to 18°, and 4 uT up to 9°.

Scored: the heading (azimuth about the chip z axis, the robot's yaw axis) of the corrected field
against the simulator's true field, RMS over the samples while the robot moves (driving or
turning; 82 % of the course), and the worst sample; and the same corrections applied to the
readings of a noise-free twin of the robot (the same course and commands), which shows the
error of the correction itself under the 0.7° a single sample's noise adds. Rows:

(a) ``no interference``: the same course and robot without K and c, through the live calibrator
    (``CalibrationSession`` with its defaults, as the node runs it, fits inline): the floor.
(b) ``static, perfect, both``: the true hard and soft iron at power-on (cold, motors
    idle: what the best static calibration done standing there holds) applied to every
    reading: the heading error the robot's own field alone causes; also with only the
    current's field, and only the temperature's.
(c) ``live calibrator, today``: the live calibrator with its defaults from power-on, no
    compensation (it calibrates itself on the first turn in place, then refines as it would);
    scored from its first calibration on.
(d) ``live calibrator, compensating``: the same with its inputs (``feed``: the die temperature
    of each row, and its battery current as ``interference_inputs``), learning K and c live;
    the learned K and c are judged against ``interference_truth``; scored also from the first
    compensation in force on, and with its final calibration over the whole course. ``no
    interference, compensating``: the floor's course with the same inputs, to show nothing is
    learned from nothing (the heading difference to the floor's row).
(e) ``quick procedure first``: the course with ``motion.QUICK_PROCEDURE`` (32 s straight ahead
    and back at three speeds) after its first turn in place, ``~/learn_compensation``
    (``CalibrationSession.request_compensation``) called as it starts; scored over the rest of
    the course (the same legs as (d) after its first turn); its answer's time and K, c.
(f) ``~/calibrate`` asked as (e)'s ``~/learn_compensation`` answers, the robot having driven
    straight since its first turn (``calibrate_after_learning``): its answer, and that of the
    same robot without the current's field asked at the same moment.

    python benchmarks/bench_interference.py                 # three seeds, a few minutes
    python benchmarks/bench_interference.py --seeds 1       # quicker
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time

import numpy as np

from mag_calibrator_ros.calibration.live.session import CalibrationSession, Processed
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel, CourseRecording, course_recording
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.tools.demo import (
    FIELD_UT,
    GROUND_HARD_IRON_UT,
    GROUND_WOBBLE_DEG,
    INCLINATION_DEG,
    SOFT_IRON,
    azimuth_errors_deg,
)

RATE_HZ = 100.0
FULL_CURRENT_FIELD_UT = 8.0
"""Along the chip x axis, at the full current (both wheels at top speed)."""
DRIFT_UT_PER_C = 0.2
"""Along the chip y axis."""
COLD_C = 20.0
WARM_UP_C = 20.0
WARM_UP_TIME_CONSTANT_S = 60.0
FRAME_ID = 'imu_link'
POLL_EVERY = 10
"""Rows between session polls (the node polls on a timer; 10 rows: 0.1 s of stream)."""


def robot(seed: int, interference: bool = True, current: bool = True,
          temperature: bool = True, noise_ut: float = 0.3) -> BoardModel:
    """The benchmark's simulated ground robot, its own field on or off (or only the current's,
    only the temperature's)."""
    drive = motion.DriveCurrent()
    trajectory = motion.CmdVelTrajectory(seed=seed, wobble_deg=GROUND_WOBBLE_DEG, drive=drive)
    per_ampere = FULL_CURRENT_FIELD_UT / drive.full_a
    config = SimConfig(
        field_ut=FIELD_UT, inclination_deg=INCLINATION_DEG, hard_iron_ut=GROUND_HARD_IRON_UT,
        soft_iron=SOFT_IRON, noise_ut=noise_ut, motion='cmd_vel', seed=seed,
        temperature_c=COLD_C, temperature_rise_c=WARM_UP_C,
        temperature_time_constant_s=WARM_UP_TIME_CONSTANT_S,
        current_field_ut_per_a=((per_ampere, 0.0, 0.0) if interference and current
                                else (0.0, 0.0, 0.0)),
        hard_iron_drift_ut_per_c=((0.0, DRIFT_UT_PER_C, 0.0) if interference and temperature
                                  else (0.0, 0.0, 0.0)),
    )
    return BoardModel(config, trajectory)


BATTERY = 'battery_state:sensor_msgs/msg/BatteryState:current'
COMPENSATING = SessionSettings(interference_inputs=(BATTERY,))


def feed(session: CalibrationSession, recording: CourseRecording, index: int,
         inputs: bool = False) -> Processed:
    """One row through the session as the node passes it (the IMU sample first, same stamp);
    ``inputs``: the row's die temperature and battery current first, as the node's
    imu/temperature and battery_state subscriptions hand them over."""
    stamp = round(recording.times[index] * 1e9)
    if inputs:
        session.process_temperature(stamp, float(recording.temperature_c[index]))
        session.process_input(0, stamp, float(recording.current_a[index]))
    session.process_imu(stamp, FRAME_ID, recording.accel[index], recording.gyro[index])
    processed = session.process(stamp, FRAME_ID, recording.mag[index])
    if index % POLL_EVERY == 0:
        session.poll()
    return processed


def live(recording: CourseRecording, clean: CourseRecording,
         settings: SessionSettings | None = None, inputs: bool = False
         ) -> tuple[np.ndarray, np.ndarray, float | None, CalibrationSession, float | None]:
    """(corrected rows, NaN until calibrated; the same calibrations applied to the noise-free
    ``clean`` twin's rows; stream seconds of the first calibration; the session; stream seconds
    from which a learned compensation was in force, None: never) of the live calibrator over
    the course."""
    session = CalibrationSession(settings or SessionSettings())
    compensated_from = None
    corrected = np.full_like(recording.mag, math.nan)
    noise_free = np.full_like(recording.mag, math.nan)
    first = None
    for index in range(len(recording.times)):
        processed = feed(session, recording, index, inputs)
        if processed.corrected is not None:
            corrected[index] = processed.corrected
            noise_free[index] = processed.calibration.apply(  # its compensation's inputs too
                clean.mag[index], [recording.current_a[index]], recording.temperature_c[index])
            if first is None:
                first = float(recording.times[index])
            if compensated_from is None and processed.calibration.compensation:
                compensated_from = float(recording.times[index])
    session.close()
    return corrected, noise_free, first, session, compensated_from


def quick(seed: int) -> tuple[CourseRecording, CourseRecording, np.ndarray, np.ndarray,
                               CalibrationSession, float, float | None, str]:
    """The course with the quick procedure after its first turn: (recording, noise-free twin,
    corrected, the same corrections noise-free, session, stream seconds the course resumes,
    seconds from the request to its answer, the answer)."""
    legs = (*motion.GROUND_COURSE[:2], *motion.QUICK_PROCEDURE, *motion.GROUND_COURSE[2:])
    starts = float(sum(leg.duration_s for leg in motion.GROUND_COURSE[:2]))
    resumes = starts + sum(leg.duration_s for leg in motion.QUICK_PROCEDURE)
    recording, clean = (course_recording(robot(seed, noise_ut=noise), motion.CourseDriver(legs),
                                         rate_hz=RATE_HZ) for noise in (0.3, 0.0))
    session = CalibrationSession(COMPENSATING)
    corrected = np.full_like(recording.mag, math.nan)
    noise_free = np.full_like(recording.mag, math.nan)
    ticket, asked, took, answer = None, None, None, 'not asked: no calibration before the course'
    for index in range(len(recording.times)):
        now = float(recording.times[index])
        if ticket is None and now >= starts and session.calibration is not None \
                and now < resumes:
            ticket, asked = session.request_compensation(60.0), now
        processed = feed(session, recording, index, inputs=True)
        for event in session.take_events():
            if ticket is not None and event.ticket == ticket and event.attempt is not None:
                took, answer = now - asked, event.attempt.message
        if processed.corrected is not None:
            corrected[index] = processed.corrected
            noise_free[index] = processed.calibration.apply(
                clean.mag[index], [recording.current_a[index]], recording.temperature_c[index])
    session.close()
    return recording, clean, corrected, noise_free, session, resumes, took, answer


def calibrate_after_learning(seed: int, current: bool = True,
                             ask_at: float | None = None) -> tuple[str, str, float]:
    """(e)'s first turn and quick procedure, and ``~/calibrate`` asked as the request for the
    own field answers: (that answer, ~/calibrate's, the stream seconds it was asked). A
    compensation put in force emptied the buffer until stop 34, and the straight legs since
    could not calibrate. ``current`` False and ``ask_at``: the twin without the current's
    field (the die's drift it has, as the learned compensation does not yet hold it), asked
    then: what the buffer holds when K needs no compensating."""
    legs = (*motion.GROUND_COURSE[:2], *motion.QUICK_PROCEDURE)
    starts = float(sum(leg.duration_s for leg in motion.GROUND_COURSE[:2]))
    recording = course_recording(robot(seed, current=current),
                                 motion.CourseDriver(legs), rate_hz=RATE_HZ)
    session = CalibrationSession(COMPENSATING)
    learning = calibrating = None
    answers, asked = {}, math.nan
    for index in range(len(recording.times)):
        now = float(recording.times[index])
        if ask_at is None and learning is None and now >= starts and session.calibration:
            learning = session.request_compensation(60.0)
        if ask_at is not None and calibrating is None and now >= ask_at:
            calibrating, asked = session.request_calibration(), now
        feed(session, recording, index, inputs=True)
        for event in session.take_events():
            if event.attempt is not None and event.ticket is not None \
                    and event.ticket in (learning, calibrating):
                answers[event.ticket] = event.attempt.message
                if event.ticket == learning:
                    calibrating, asked = session.request_calibration(), now
        if calibrating in answers:
            break
    session.close()
    return answers.get(learning, 'not asked'), answers.get(calibrating, 'no answer'), asked


def static_perfect(board: BoardModel, recording: CourseRecording) -> np.ndarray:
    """The true power-on calibration (cold, motors idle) applied to every row."""
    config = board.config
    idle = board.trajectory.drive.idle_a
    offset = (config.hard_iron + config.current_field * idle) * 1e-6
    return np.linalg.solve(config.soft_iron_matrix, (recording.mag - offset).T).T


def heading(corrected: np.ndarray, recording: CourseRecording, since: float = -math.inf
            ) -> tuple[float, float, int]:
    """(RMS, worst |error| in degrees, samples) over the rows moving and corrected (from
    ``since`` seconds on)."""
    keep = (recording.moving & np.all(np.isfinite(corrected), axis=1)
            & (recording.times >= since))
    if not np.any(keep):
        return math.nan, math.nan, 0
    errors = azimuth_errors_deg(corrected[keep], recording.truth[keep])
    return float(np.sqrt(np.mean(errors**2))), float(np.max(np.abs(errors))), int(keep.sum())


def one_seed(seed: int) -> dict[str, tuple[float, float, int, float]]:
    """Per row: (RMS, worst, samples, RMS of the same corrections on noise-free readings)."""
    results = {}

    def record(**kwargs) -> tuple[BoardModel, CourseRecording, CourseRecording]:
        board = robot(seed, **kwargs)
        return (board, course_recording(board, rate_hz=RATE_HZ),
                course_recording(robot(seed, noise_ut=0.0, **kwargs), rate_hz=RATE_HZ))

    _, quiet, clean = record(interference=False)
    corrected, noise_free, _, _, _ = live(quiet, clean)
    results['no interference, live calibrator'] = (*heading(corrected, quiet),
                                                   heading(noise_free, clean)[0])
    compensating, noise_free, _, session, _ = live(quiet, clean, COMPENSATING, inputs=True)
    results['no interference, compensating'] = (*heading(compensating, quiet),
                                                heading(noise_free, clean)[0])
    both = np.all(np.isfinite(corrected) & np.isfinite(compensating), axis=1) & quiet.moving
    difference = azimuth_errors_deg(compensating[both], corrected[both]) if both.any() else []
    learned = session.calibration.compensation if session.calibration else None
    print(f'seed {seed}: no interference: compensation in force {learned}; adoptions '
          f'{session.report().counts.adoptions}; heading difference to the floor '
          f'{float(np.sqrt(np.mean(np.square(difference)))):.3f}° RMS', flush=True)
    for name, kind in (('current', {'temperature': False}), ('temperature', {'current': False}),
                       ('both', {})):
        board, recording, clean = record(**kind)
        results[f'static, perfect, {name}'] = (
            *heading(static_perfect(board, recording), recording),
            heading(static_perfect(board, clean), clean)[0])
    corrected, noise_free, first, session, _ = live(recording, clean)
    results['live calibrator, today'] = (*heading(corrected, recording),
                                         heading(noise_free, clean)[0])
    truth = board.interference_truth()
    corrected, noise_free, _, learning, since = live(recording, clean, COMPENSATING,
                                                    inputs=True)
    results['live calibrator, compensating'] = (*heading(corrected, recording),
                                                heading(noise_free, clean)[0])
    if since is not None:
        results['  the same, once compensating'] = (*heading(corrected, recording, since),
                                                   heading(noise_free, clean, since)[0])
        final = learning.calibration  # learned by the end, applied to the whole course
        inputs = recording.current_a[:, None]
        results['  its final calibration, whole course'] = (
            *heading(final.apply(recording.mag, inputs, recording.temperature_c), recording),
            heading(final.apply(clean.mag, inputs, clean.temperature_c), clean)[0])
    first_turn = sum(leg.duration_s for leg in motion.GROUND_COURSE[:2])
    results['  the same, after the first turn'] = (
        *heading(corrected, recording, first_turn), heading(noise_free, clean, first_turn)[0])
    record_q, clean_q, corrected_q, noise_free_q, session_q, resumes, took, answer = quick(seed)
    results['quick procedure first, then the course'] = (
        *heading(corrected_q, record_q, resumes), heading(noise_free_q, clean_q, resumes)[0])
    learned_q = session_q.calibration.compensation if session_q.calibration else None
    print(f'seed {seed}: quick procedure answered after {took} s: {answer}; K = '
          f'{None if learned_q is None else learned_q.interference[:, 0] * 1e6} uT/A, c = '
          f'{None if learned_q is None else learned_q.temperature_coefficient * 1e6} uT/°C '
          f'at the end; adoptions {session_q.report().counts.adoptions}', flush=True)
    learned_answer, calibrated, asked = calibrate_after_learning(seed)
    _, twin, _ = calibrate_after_learning(seed, current=False, ask_at=asked)
    print(f'seed {seed}: ~/calibrate as ~/learn_compensation answered ({learned_answer[:60]}'
          f"...) at {asked:.1f} s: {calibrated}\n  the twin without the current's field, "
          f'asked then: {twin}', flush=True)
    learned = learning.calibration.compensation if learning.calibration else None
    report = learning.report()
    if learned is not None:
        print(f'seed {seed}: learned K = {learned.interference[:, 0] * 1e6} uT/A, c = '
              f'{learned.temperature_coefficient * 1e6} uT/°C around '
              f'{learned.reference_temperature} °C; adoptions {report.counts.adoptions}, the '
              f'first at {since} s; needs: {report.compensation_needs or "nothing"}',
              flush=True)
    else:
        print(f'seed {seed}: nothing learned: {report.compensation_needs}', flush=True)
    print(f'seed {seed}: first calibration at {first} s of the course '
          f'({session.calibration.model if session.calibration else "none"}, adoptions '
          f'{session.report().counts.adoptions}); current {recording.current_a.min():.2f}-'
          f'{recording.current_a.max():.2f} A, die {recording.temperature_c[0]:.1f}-'
          f'{recording.temperature_c[-1]:.1f} °C; truth K = {truth.current_field * 1e6} uT/A, '
          f'c = {truth.temperature_drift * 1e6} uT/°C, T0 = {truth.reference_temperature_c} °C',
          flush=True)
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    args = parser.parse_args(argv)
    started = time.monotonic()
    runs = [one_seed(seed) for seed in args.seeds]
    print(f'\nHeading RMS while driving (worst sample), seeds {args.seeds}, '
          f'{time.monotonic() - started:.0f} s:')
    names = list(dict.fromkeys(name for run in runs for name in run))
    for name in names:
        rows = [run[name] for run in runs if name in run]
        rms, clean = [row[0] for row in rows], [row[3] for row in rows]
        worst = max(row[1] for row in rows)
        print(f'  {name:38s} {min(rms):6.2f}-{max(rms):6.2f}° RMS (median '
              f'{statistics.median(rms):.2f}°), worst {worst:6.2f}°, '
              f'{rows[0][2]} samples; noise-free {min(clean):.2f}-{max(clean):.2f}°')
    return 0


if __name__ == '__main__':
    sys.exit(main())
