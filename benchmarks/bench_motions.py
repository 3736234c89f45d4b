#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Motions of ordinary use (issue #44) replayed through the live calibrator.

The simulated board (50 uT at 60° dip, hard iron (25, -15, 10) uT, mild soft iron, noise 0.3 uT,
gyroscope bias (0.3, -0.2, 0.4) °/s; the magnetometer at 100 Hz, the accelerometer and gyroscope
at 225 Hz with DLPF 3's noise bandwidths, as the driver's defaults) moves in each of the
``sim/motion.py`` motions of ordinary use, three seeds each:

- ``wrist``: a hand turning the board within 90° of a base pose (a partial sphere), 90 s;
- ``drone``: tilts of at most 30° and yaw turns, the accelerometer reading the thrust, 90 s;
  ``drone_level``: the same attitudes with the accelerometer reading gravity (no thrust);
- ``magnet``: a hand tumbling the board (``tumble``, which today's engine calibrates), a magnet
  of 20-60 uT in a seeded direction stuck on at 40 s and taken off at 100 s, 160 s;
- ``zone``: the same tumbling carried along a path (``CarriedTrajectory``) into a world-fixed
  zone of 30 uT (a seeded direction, 1.5 m radius) at 60-66 s, about in it, out at 94-100 s,
  160 s.

Each stream goes through ``CalibrationSession`` with its default settings, in stamp order as the
node gets it (``process_imu`` for each inertial sample, ``process`` for each reading, ``poll``
after each reading; fits inline). Reported per run: the time of the first calibration in force;
the direction error (deg) of the corrected field against the true earth field in the body frame
from then on (median, p95); how many calibrations went in force; for ``magnet`` the time to
re-learn after the attachment and after the removal (from then on to the phase's end the error of
every 1 s stretch's median below 5°; ``never``: not by the phase's end) and the median error of
each phase; for ``zone`` how many calibrations went in force while the board was inside or
within 10 s of leaving (``adopted in zone``), the median error inside, and the median and p95
after it left.

    python benchmarks/bench_motions.py [--seeds 3] [--cases wrist,drone] [--json out.json]
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
import json
import math
import time

import numpy as np

from mag_calibrator_ros.calibration.live.events import Processed
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel
from mag_calibrator_ros.sim.config import SimConfig

MAG_HZ = 100.0
IMU_HZ = reg.INTERNAL_RATE_HZ / 5.0  # the driver's imu_rate_hz 200 -> 225 Hz
ACCEL_NBW = reg.ACCEL_DLPF_HZ[3][1]
GYRO_NBW = reg.GYRO_DLPF_HZ[3][1]
BOARD = {'field_ut': 50.0, 'inclination_deg': 60.0, 'hard_iron_ut': (25.0, -15.0, 10.0),
         'soft_iron': (1.08, 0.04, -0.02, 0.04, 0.94, 0.03, -0.02, 0.03, 1.0), 'noise_ut': 0.3,
         'gyro_bias_dps': (0.3, -0.2, 0.4)}
ATTACH_S, REMOVE_S = 40.0, 100.0
ZONE_RADIUS_M = 1.5
ZONE_PATH = ((0.0, (-4.0, 0.0, 0.0)), (60.0, (-4.0, 0.0, 0.0)), (66.0, (0.0, 0.0, 0.0)),
             (80.0, (0.5, 0.3, 0.0)), (94.0, (-0.3, -0.3, 0.0)), (100.0, (4.0, 0.0, 0.0)))
"""Outside for a minute, into the zone, about in it for half a minute, and out."""
ZONE_AFTER_S = 10.0
RELEARN_DEG = 5.0
CASES = ('wrist', 'drone', 'drone_level', 'magnet', 'zone')


def _direction(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def make_board(case: str, seed: int) -> tuple[BoardModel, float]:
    """The board of ``case`` for ``seed`` and how long it runs (s)."""
    rng = np.random.default_rng([seed, 44])
    if case == 'wrist':
        return BoardModel(SimConfig(seed=seed, **BOARD), motion.WristTrajectory(seed)), 90.0
    if case in ('drone', 'drone_level'):
        drone = motion.DroneTrajectory(seed, thrust=case == 'drone')
        return BoardModel(SimConfig(seed=seed, **BOARD), drone), 90.0
    if case == 'magnet':
        magnet = _direction(rng) * rng.uniform(20.0, 60.0)
        config = SimConfig(seed=seed, attached_magnet_ut=tuple(magnet),
                           magnet_attached_s=ATTACH_S, magnet_removed_s=REMOVE_S, **BOARD)
        return BoardModel(config, motion.TumbleTrajectory(seed)), 160.0
    if case == 'zone':
        config = SimConfig(seed=seed, zone_field_ut=tuple(_direction(rng) * 30.0),
                           zone_radius_m=ZONE_RADIUS_M, **BOARD)
        carried = motion.CarriedTrajectory(motion.TumbleTrajectory(seed), ZONE_PATH)
        return BoardModel(config, carried), 160.0
    raise ValueError(f'unknown case {case!r}')


def stream(board: BoardModel, seconds: float, session: CalibrationSession | None = None
           ) -> Iterator[tuple[float, Processed, np.ndarray]]:
    """The board's readings through ``session`` (a default one if None; closed at the end) as
    the node streams them: per magnetometer reading its time, what ``process`` made of it and
    the true earth field (T)."""
    session = session or CalibrationSession(SessionSettings())
    n_mag, n_imu = int(seconds * MAG_HZ), int(seconds * IMU_HZ)
    imu = 0
    try:
        for k in range(n_mag):
            t = k / MAG_HZ
            while imu < n_imu and imu / IMU_HZ <= t:  # stamp order, the IMU first on a tie
                t_imu = imu / IMU_HZ
                accel, gyro, _ = board.inertial(t_imu, ACCEL_NBW, GYRO_NBW)
                session.process_imu(round(t_imu * 1e9), 'imu_link', accel.tolist(), gyro.tolist())
                imu += 1
            sensed, truth = board.magnetometer(t)
            processed = session.process(round(t * 1e9), 'imu_link', (sensed * 1e-6).tolist())
            session.poll()
            session.take_events()
            yield t, processed, truth
    finally:
        session.close()


def replay(board: BoardModel, seconds: float) -> dict[str, np.ndarray]:
    """Per magnetometer reading of ``stream``: its time, error (deg; inf while uncalibrated),
    the index of the calibration in force and the zone's weight."""
    times, errors, calibrations, zone = [], [], [], []
    in_force: list[object] = []
    for t, processed, truth in stream(board, seconds):
        error = math.inf
        if processed.corrected is not None:
            corrected = np.asarray(processed.corrected, dtype=float)
            cosine = corrected @ truth / (np.linalg.norm(corrected) * np.linalg.norm(truth))
            error = math.degrees(math.acos(min(1.0, max(-1.0, float(cosine)))))
        if processed.calibration is not None and (
                not in_force or in_force[-1] is not processed.calibration):
            in_force.append(processed.calibration)
        times.append(t)
        errors.append(error)
        calibrations.append(len(in_force) - 1)
        zone.append(board.zone_weight(t))
    return {'t': np.array(times), 'error': np.array(errors),
            'calibration': np.array(calibrations), 'zone': np.array(zone)}


def _stats(errors: np.ndarray) -> tuple[float | None, float | None]:
    errors = errors[np.isfinite(errors)]
    if len(errors) == 0:
        return None, None
    return float(np.median(errors)), float(np.percentile(errors, 95))


def relearn_s(run: dict[str, np.ndarray], start: float, end: float) -> float | None:
    """Seconds from ``start`` until every 1 s stretch's median error stays below RELEARN_DEG to
    ``end`` (None: not by then)."""
    bins = np.arange(start, end, 1.0)
    medians = []
    for edge in bins:
        chosen = run['error'][(run['t'] >= edge) & (run['t'] < edge + 1.0)]
        medians.append(float(np.median(chosen)) if len(chosen) else math.inf)
    good = np.array(medians) < RELEARN_DEG
    if len(good) == 0 or not good[-1]:
        return None
    bad = np.flatnonzero(~good)
    return float(bins[bad[-1] + 1] - start) if len(bad) else 0.0


def score(case: str, seed: int) -> dict[str, object]:
    board, seconds = make_board(case, seed)
    started = time.perf_counter()
    run = replay(board, seconds)
    calibrated = run['calibration'] >= 0
    first = float(run['t'][calibrated][0]) if calibrated.any() else None
    after = run['error'][calibrated]
    median, p95 = _stats(after)
    row: dict[str, object] = {
        'case': case, 'seed': seed, 'seconds': seconds, 'first_s': first,
        'median_deg': median, 'p95_deg': p95,
        'adopted': int(run['calibration'].max() + 1),
        'replay_s': round(time.perf_counter() - started, 1)}
    if case == 'magnet':
        row['relearn_attach_s'] = relearn_s(run, ATTACH_S, REMOVE_S)
        row['relearn_remove_s'] = relearn_s(run, REMOVE_S, seconds)
        on = (run['t'] >= ATTACH_S) & (run['t'] < REMOVE_S)
        row['median_on_deg'] = _stats(run['error'][on])[0]
        row['median_off_deg'] = _stats(run['error'][run['t'] >= REMOVE_S])[0]
    if case == 'zone':
        inside = run['zone'] > 0.0
        exit_s = float(run['t'][inside][-1])
        near = (run['t'] >= run['t'][inside][0]) & (run['t'] <= exit_s + ZONE_AFTER_S)
        changes = np.flatnonzero(np.diff(run['calibration']) > 0) + 1
        row['adopted_in_zone'] = int(np.sum(near[changes]))
        row['median_inside_deg'] = _stats(run['error'][inside])[0]
        row['median_after_deg'], row['p95_after_deg'] = _stats(
            run['error'][run['t'] > exit_s + 1.0])
    return row


def _cell(value: object, digits: int = 2) -> str:
    if value is None:
        return 'never' if digits == 1 else '-'
    if isinstance(value, float):
        return f'{value:.{digits}f}'
    return str(value)


def table(rows: list[dict[str, object]]) -> str:
    head = (f"{'case':<12}{'seed':>5}{'first s':>9}{'median°':>9}{'p95°':>9}{'fits':>6}  "
            'disturbance')
    lines = [head, '-' * len(head)]
    for row in rows:
        extra = ''
        if row['case'] == 'magnet':
            extra = (f"re-learn after attach {_cell(row['relearn_attach_s'], 1)} s, "
                     f"after removal {_cell(row['relearn_remove_s'], 1)} s; median on "
                     f"{_cell(row['median_on_deg'])}°, off {_cell(row['median_off_deg'])}°")
        elif row['case'] == 'zone':
            extra = (f"adopted in zone {row['adopted_in_zone']}; median inside "
                     f"{_cell(row['median_inside_deg'])}°, after {_cell(row['median_after_deg'])}"
                     f"° (p95 {_cell(row['p95_after_deg'])}°)")
        lines.append(f"{row['case']:<12}{row['seed']:>5}{_cell(row['first_s'], 1):>9}"
                     f"{_cell(row['median_deg']):>9}{_cell(row['p95_deg']):>9}"
                     f"{row['adopted']:>6}  {extra}")
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, default=3)
    parser.add_argument('--cases', default=','.join(CASES),
                        help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument('--json', metavar='PATH', help='also write the rows as JSON')
    args = parser.parse_args(argv)
    cases = [case for case in args.cases.split(',') if case]
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        parser.error(f"unknown case(s): {', '.join(unknown)}")
    rows = []
    for case in cases:
        for seed in range(args.seeds):
            rows.append(score(case, seed))
            print(f"  {case} seed {seed}: {rows[-1]['replay_s']} s", flush=True)
    print(table(rows))
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as out:
            json.dump(rows, out, indent=2)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
