#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""K learned offline on a saved calibration from a drive that never turns
(``mag_calibrator_fit --calibration``), judged by the heading it gives over a whole course.

The simulated ground robot of ``bench_interference.py`` (8 uT along x at full current,
0.2 uT/degC along y) is calibrated as ``~/rotate_and_calibrate`` calibrates it: turning in place
both ways (TURNS), its readings written as a CSV without the current and fitted, so the saved
offset holds the field of the current turning draws. Then the same
robot runs ``motion.QUICK_PROCEDURE`` (straight ahead and back at three speeds, no turn) into a
rosbag2 with its IMU, battery current and temperature, fitted with ``--calibration``. Printed per
seed: the exit status, K against the truth, the answer's median |B| error on the drive, and the
heading RMS over a second run of the whole course (K and c applied, the mean aside) of: the
saved static calibration alone, and the calibration written (on exit 1, that of a rerun with
--max-residual 100, which also loosens the fits' own residual gate: an estimate).

    PYTHONPATH=$PWD python benchmarks/bench_fit_start.py --seeds 1 2 3
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'test'))
from bench_fit_compensation import heading_rms_deg  # noqa: E402
from bench_interference import robot  # noqa: E402
from test_fit_cli_compensation import write_csv, write_rosbag2  # noqa: E402

from mag_calibrator_ros.sim import motion  # noqa: E402
from mag_calibrator_ros.sim.board import course_recording  # noqa: E402
from mag_calibrator_ros.tools import fit  # noqa: E402

RATE_HZ = 50.0
TURNS = (motion.Leg(2.0), motion.Leg(14.0, yaw_rate=0.5), motion.Leg(2.0),
         motion.Leg(12.0, yaw_rate=-0.6), motion.Leg(2.0))


def cli(*argv: object) -> tuple[int, dict]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = fit.main([str(a) for a in argv] + ['--json'])
    return status, json.loads(out.getvalue())


def one_seed(seed: int, directory: Path) -> str:
    board = robot(seed)
    turns = course_recording(board, motion.CourseDriver(TURNS), rate_hz=RATE_HZ)
    static = directory / f'static_{seed}.yaml'
    status, _ = cli(write_csv(directory / f'turns_{seed}.csv', turns, columns=()), '--units',
                    'T', '--output', static)
    if status != 0:
        return f'seed {seed}: the static calibration failed its gates (exit {status})'
    drive = course_recording(board, motion.CourseDriver(motion.QUICK_PROCEDURE),
                             rate_hz=RATE_HZ, start_s=turns.times[-1] + 1.0)
    bag = write_rosbag2(directory / f'drive_{seed}', drive, imu=True)
    written = directory / f'learned_{seed}.yaml'
    status, summary = cli(bag, '--accel', '/imu', '--calibration', static, '--output', written)
    found = summary['compensation']
    if not found['learned']:
        return f'seed {seed}: exit {status}, nothing learned: {found["needs"]}'
    if not written.exists():  # exit 1: what it would have written, to measure it
        cli(bag, '--accel', '/imu', '--calibration', static, '--max-residual', '100',
            '--output', written)
    again = course_recording(robot(seed), rate_hz=RATE_HZ)
    [k] = found['interference'].values()
    truth = board.interference_truth()
    return (f'seed {seed}: exit {status}; K = {np.round(np.array(k) * 1e6, 3)} uT/A (truth '
            f'{truth.current_field * 1e6}); |B| median error on the drive '
            f"{summary['start']['check']['median_error_pct']:.2f} %; heading RMS over the "
            f'course: the saved static alone {heading_rms_deg(static, again):.2f} deg, with '
            f'K learned {heading_rms_deg(written, again):.2f} deg')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as directory:
        for seed in args.seeds:
            print(one_seed(seed, Path(directory)), flush=True)


if __name__ == '__main__':
    main()
