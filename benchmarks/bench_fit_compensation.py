#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""K and c learned offline by ``mag_calibrator_fit`` from a log of the driven course.

The simulated ground robot of ``bench_interference.py`` (8 uT along x at full current,
0.2 uT/degC along y over a 20 degC warm-up) drives ``motion.GROUND_COURSE``; its magnetometer,
battery current and die temperature are written as a CSV (``time,mx,my,mz,current,temperature``,
tesla, the course's rate) and fitted by the CLI as a user would: ``mag_calibrator_fit log.csv
--units T --json``. Prints the learned K, c and T0 per seed against the simulated truth, and
the share of the robot's field the model misses over the course (RMS of the modelled minus the
true field's variation, % of the true field's variation), and the heading RMS of the calibration
it writes (``--output``, K and c applied) over the course.

    PYTHONPATH=$PWD python benchmarks/bench_fit_compensation.py --seeds 1 2 3 --rate 50
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
from bench_interference import robot  # noqa: E402

from mag_calibrator_ros.calibration.store.calibration_file import load_calibration  # noqa: E402
from mag_calibrator_ros.sim.board import course_recording  # noqa: E402
from mag_calibrator_ros.tools import fit  # noqa: E402


def one_seed(seed: int, rate_hz: float, directory: Path) -> str:
    board = robot(seed)
    recording = course_recording(board, rate_hz=rate_hz)
    truth = board.interference_truth()
    path = directory / f'course_{seed}.csv'
    lines = ['time,mx,my,mz,current,temperature']
    for i, t in enumerate(recording.times.tolist()):
        lines.append(','.join([f'{t:.3f}', *(f'{v:.9g}' for v in recording.mag[i]),
                               f'{recording.current_a[i]:.4f}',
                               f'{recording.temperature_c[i]:.3f}']))
    path.write_text('\n'.join(lines) + '\n')
    out = io.StringIO()
    written = directory / f'calibration_{seed}.yaml'
    with contextlib.redirect_stdout(out):
        status = fit.main([str(path), '--units', 'T', '--json', '--output', str(written)])
    found = json.loads(out.getvalue())['compensation']
    heading = (f'; the calibration written: heading RMS {heading_rms_deg(written, recording):.2f}'
               ' deg over the course' if written.exists() else '; no calibration written')
    if not found['learned']:
        return f'seed {seed}: exit {status}, nothing learned: {found["needs"]}'
    k = np.array(found['interference']['current'])
    c = np.array(found['temperature_coefficient'])
    modelled = np.outer(recording.current_a, k) + np.outer(recording.temperature_c, c)
    true = (np.outer(recording.current_a, truth.current_field)
            + np.outer(recording.temperature_c, truth.temperature_drift))
    error, true = modelled - true, true - true.mean(axis=0)
    error -= error.mean(axis=0)
    missed = 100 * np.sqrt(np.mean(np.sum(error**2, axis=1)) / np.mean(np.sum(true**2, axis=1)))
    return (f'seed {seed}: exit {status}; K = {np.round(k * 1e6, 3)} uT/A (truth '
            f'{truth.current_field * 1e6}; x {100 * (k[0] / truth.current_field[0] - 1):+.1f} %);'
            f' c = {np.round(c * 1e6, 3)} uT/degC (truth {truth.temperature_drift * 1e6}; y '
            f'{100 * (c[1] / truth.temperature_drift[1] - 1):+.1f} %) around T0 '
            f'{found["reference_temperature_degC"]} degC; removes {found["removed_pct"]:.2f} % '
            f"of the field; misses {missed:.1f} % of the robot field's variation{heading}")


def heading_rms_deg(written: Path, recording) -> float:
    """RMS heading error of the written calibration (K and c applied) against the simulated
    Earth field over the course, its mean (a mounting yaw) aside."""
    calibration = load_calibration(written)
    corrected = calibration.apply(recording.mag, recording.current_a[:, None],
                                  recording.temperature_c)
    error = np.angle(np.exp(1j * (np.arctan2(corrected[:, 1], corrected[:, 0])
                                  - np.arctan2(recording.truth[:, 1], recording.truth[:, 0]))))
    error -= np.angle(np.mean(np.exp(1j * error)))
    return float(np.degrees(np.sqrt(np.mean(error ** 2))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    parser.add_argument('--rate', type=float, default=50.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as directory:
        for seed in args.seeds:
            print(one_seed(seed, args.rate, Path(directory)), flush=True)


if __name__ == '__main__':
    main()
