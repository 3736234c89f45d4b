#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Calibration file load/save cost, for real files and for the hostile ones that used to hang.

Every case is timed ``--repeats`` times (fresh files in a temporary directory); the table gives
the median and the worst time in ms, and the outcome (ok or the start of the refusal). Before the
limits, the billion-laughs file and a 100 MB list file ran for minutes and took gigabytes, and a
FIFO blocked until a writer appeared.

    python benchmarks/bench_calibration_file.py
    python benchmarks/bench_calibration_file.py --repeats 50
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import statistics
import tempfile
import time

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.store.calibration_file import (
    MAX_FILE_BYTES,
    MAX_NODES,
    CalibrationFileError,
    load_calibration,
    save_calibration,
)

CALIBRATION = Calibration(
    np.array([1.2e-5, -8e-6, 6e-6]), np.array([[1.03, 0.04, -0.01], [0.04, 0.99, 0.01],
                                               [-0.01, 0.01, 1.1]]), 4.9e-5, 'full',
    {'residual_rms_pct': 0.8, 'coverage': 0.95, 'samples': 100, 'time': '2026-11-22T00:30:00Z',
     'frame_id': 'imu_link', 'units': 'T', 'rotation': [1.0, 0, 0, 0, 1, 0, 0, 0, 1]},
)
HEAD = 'mag_calibrator:\n  ros__parameters:\n    calibration:\n'
LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + ''.join(
    f'{chr(98 + i)}: &{chr(98 + i)} [' + ','.join([f'*{chr(97 + i)}'] * 9) + ']\n'
    for i in range(8))


def _load_cases(directory: Path) -> dict[str, Path]:
    def text(name: str, content: str) -> Path:
        path = directory / name
        path.write_text(content)
        return path

    save_calibration(directory / 'real.yaml', CALIBRATION)
    huge = directory / 'huge.yaml'
    with open(huge, 'wb') as file:
        file.truncate(100_000_000)
    fifo = directory / 'fifo.yaml'
    os.mkfifo(fifo)
    values = ', '.join(['1.5'] * 12_000)
    keys = ''.join(f'      key_{i}: [1.0e-05, 2.0e-05, 3.0e-05]\n' for i in range(1_300))
    return {
        'real calibration (1 kB)': directory / 'real.yaml',
        'billion laughs (1 kB)': text('laughs.yaml', LAUGHS),
        '5,000-deep nesting': text('deep.yaml', 'a: ' + '[' * 5000 + ']' * 5000),
        f'60 kB list (over {MAX_NODES} values)': text('list.yaml', f'{HEAD}      v: [{values}]\n'),
        f'{MAX_FILE_BYTES // 1024} kB of keys': text('keys.yaml', (HEAD + keys)[:MAX_FILE_BYTES]),
        '5,000-digit integer': text('digits.yaml', f'{HEAD}      n: {"1" * 5000}\n'),
        '100 MB file (sparse)': huge,
        'FIFO, no writer': fifo,
        '/dev/zero': Path('/dev/zero'),
    }


def _time(action, repeats: int) -> tuple[float, float, str]:
    times = []
    outcome = 'ok'
    for _ in range(repeats):
        start = time.perf_counter()
        try:
            action()
        except CalibrationFileError as error:
            outcome = str(error).split(': ', 1)[1][:48]
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), max(times), outcome


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=20)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as name:
        directory = Path(name)
        for case, path in _load_cases(directory).items():
            rows.append((f'load {case}', *_time(lambda p=path: load_calibration(p), args.repeats)))
        target = directory / 'saved' / 'calibration.yaml'
        rows.append(('save (atomic, fsync)',
                     *_time(lambda: save_calibration(target, CALIBRATION), args.repeats)))
        crowded = directory / 'crowded'
        crowded.mkdir()
        for index in range(10_000):
            (crowded / f'other_{index}.yaml').touch()
        rows.append(('save into a directory of 10,000 files',
                     *_time(lambda: save_calibration(crowded / 'c.yaml', CALIBRATION),
                            args.repeats)))
    print('| case | median ms | max ms | outcome |\n|---|---:|---:|---|')
    for case, median, worst, outcome in rows:
        print(f'| {case} | {median:.2f} | {worst:.2f} | {outcome} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
