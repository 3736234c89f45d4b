#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Real recordings as users have them: hand-taken logs without time, and ROS 1 bags.

(a) Hand-taken logs with an accelerometer beside the magnetometer and no time column
    (jremington's AltIMU/LSM303DLHC, ICM-20948 and LSM9DS1 AHRS projects), through
    ``mag_calibrator_fit --accel-columns 0,1,2`` with no ``--rate`` and with each ``--rate``
    from 1 to 100, buffer mode and ``--all``: what the alignment says, and the dip's scatter
    with its rotation against the best rotation of the same calibration on the same rows (the
    quasi-static readings: the clockless attitudes with |a| within 3 % of its median and
    |field| within 5 % of F). Beside it, what the clock at the guessed rate found before
    (``StaticAttitudes()`` at ``--rate``, the same estimate).
(b) ROS 1 bags of imu_tools read as they are, converted to rosbag2 (sqlite3, mcap) by rosbags,
    and written as CSV with their stamps: one calibration from every container.

    python scripts/fetch_public_recordings.py   # once: the public files, outside the repository
    python benchmarks/bench_recordings.py --data ../shared/data
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
from pathlib import Path
import sys
import tempfile
import time

import numpy as np
from rosbags.convert import convert

from mag_calibrator_ros.calibration.fit.alignment import (
    MAX_ACCEL_ERROR,
    MAX_FIELD_ERROR,
    StaticAttitudes,
    estimate_alignment,
)
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.tools import fit
from mag_calibrator_ros.tools.recording_text import read_paired_recording
from mag_calibrator_ros.tools.recordings import read_recording

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_alignment import best_rotation_std  # noqa: E402

PUBLIC = Path(os.environ.get('MAG_PUBLIC_RECORDINGS',
                             Path('~/.cache/mag_calibrator_ros/recordings').expanduser()))
LOGS = [
    # (where, file): accelerometer fields 0,1,2, magnetometer 3,4,5, no time column
    ('data', 'lsm303dlhc-altimu10v3/cal_output_2.log'),
    ('public', 'icm_20948_get_cal_data_OUTPUT'),
    ('public', 'example_Arduino_output.txt'),
]
RATES = [None, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0, 100.0]
BAGS = ['sparkfun_razor.bag', 'ardrone_imu.bag', 'phidgets_imu_upside_down.bag']
TARGET_RATIO = 1.05


def _run(argv: list[str]) -> tuple[int, dict]:
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(io.StringIO()):
        status = fit.main(argv)
    return status, json.loads(buffer.getvalue()) if buffer.getvalue() else {}


def quasi_static(recording, calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """The clockless attitudes' corrected field and specific force, screened as the estimate
    screens them (|a| near its median, |field| near F)."""
    attitudes = StaticAttitudes(clock=False)
    attitudes.field_scale = float(np.mean(np.ptp(recording.samples, axis=0))) / 2.0
    for field, force in zip(recording.samples, recording.accel, strict=True):
        attitudes.add(0.0, field, force)
    attitudes.finish()
    rows = attitudes.snapshot()
    field = calibration.unrotated(rows[:, :3])
    accel = rows[:, 3:6]
    norms = np.linalg.norm(accel, axis=1)
    static = np.abs(norms / np.median(norms) - 1) <= MAX_ACCEL_ERROR
    static &= np.abs(np.linalg.norm(field, axis=1) / calibration.field_strength
                     - 1) <= MAX_FIELD_ERROR
    return field[static], accel[static]


def clocked_at(recording, calibration: Calibration, rate: float) -> str:
    """What the clock at a guessed rate found (the behaviour before logs went clockless)."""
    attitudes = StaticAttitudes()
    attitudes.field_scale = float(np.mean(np.ptp(recording.samples, axis=0))) / 2.0
    for k, (field, force) in enumerate(zip(recording.samples, recording.accel, strict=True)):
        attitudes.add(k / rate, field, force)
    attitudes.finish()
    alignment = estimate_alignment(attitudes.snapshot(), calibration)
    return _verdict(alignment.success, alignment.remap, alignment.reason)


def _verdict(applied: bool, remap: str, reason: str) -> str:
    if applied:
        return 'aligned'
    if remap:
        return f'remap {remap}'
    return 'refused: ' + reason.split('(')[0].strip()


def logs(data: Path) -> list[dict]:
    rows = []
    for where, name in LOGS:
        path = (data if where == 'data' else PUBLIC) / name
        if not path.is_file():
            print(f'  (skipped {name}: not in {path.parent}; run scripts/'
                  'fetch_public_recordings.py)', file=sys.stderr)
            continue
        recording = read_paired_recording(path, accel_columns='0,1,2')
        for mode in ([], ['--all']):
            for rate in RATES:
                option = [] if rate is None else ['--rate', str(rate)]
                _, summary = _run([str(path), '--accel-columns', '0,1,2', '--json', *mode,
                                   *option])
                alignment = summary['alignment']
                calibration = Calibration(summary['offset'], summary['matrix'],
                                          summary['field_strength'])
                field, accel = quasi_static(recording, calibration)
                before, best = best_rotation_std(field, accel)
                rotation = np.reshape(alignment['rotation'], (3, 3))
                ours = best_rotation_std(field @ rotation.T, accel)[0]
                rows.append({
                    'log': Path(name).name, 'mode': 'all' if mode else 'buffer',
                    'rate': 'none' if rate is None else f'{rate:g}',
                    'said': _verdict(alignment['applied'], alignment['remap'],
                                     alignment['reason']),
                    'static': len(field), 'before': before, 'best': best, 'ours': ours,
                    'before_clockless': (clocked_at(recording, calibration, rate)
                                         if rate is not None else
                                         clocked_at(recording, calibration, 100.0)),
                })
    return rows


def bags() -> list[dict]:
    rows = []
    keys = ('success', 'reason', 'model', 'offset', 'matrix', 'field_strength')
    for name in BAGS:
        bag = PUBLIC / name
        if not bag.is_file():
            print(f'  (skipped {name}: not in {PUBLIC})', file=sys.stderr)
            continue
        with tempfile.TemporaryDirectory() as tmp:
            recording = read_recording(bag, accel_topic='')
            csv = Path(tmp) / 'bag.csv'
            lines = ['time,mx,my,mz,ax,ay,az']
            lines += [','.join(repr(v) for v in (t, *m, *a)) for t, m, a in zip(
                recording.stamps.tolist(), recording.samples.tolist(), recording.accel.tolist(),
                strict=True)]
            csv.write_text('\n'.join(lines) + '\n')
            inputs = {'ROS 1': [str(bag), '--accel']}
            for storage in ('sqlite3', 'mcap'):
                target = Path(tmp) / storage
                convert([bag], target, storage, 9, None, 'file', None, None, [], [], [], [])
                inputs[f'rosbag2 {storage}'] = [str(target), '--accel']
            inputs['CSV'] = [str(csv), '--accel-columns', 'ax,ay,az', '--units', 'T']
            results = {}
            for label, argv in inputs.items():
                started = time.perf_counter()
                status, summary = _run([*argv, '--json'])
                seconds = time.perf_counter() - started
                results[label] = (status, json.dumps({k: summary[k] for k in keys}), seconds,
                                  summary)
            reference = results['ROS 1']
            for label, (status, calibration, seconds, summary) in results.items():
                rows.append({'bag': name, 'input': label, 'status': status,
                             'rows': summary['input']['rows'],
                             'skipped': sum(summary['input']['skipped'].values()),
                             'same': calibration == reference[1] and status == reference[0],
                             'seconds': seconds, 'reason': summary['reason'][:60]})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--data', type=Path, default=Path('../shared/data'))
    args = parser.parse_args()

    print('(a) hand-taken logs without time: alignment by --rate (none = not given)')
    print('| log | mode | --rate | says | rows | none deg | best deg | ours deg | ours/best | '
          'before: clock at --rate |')
    print('|---|---|---|---|---:|---:|---:|---:|---:|---|')
    logged = logs(args.data)
    for row in logged:
        print(f"| {row['log']} | {row['mode']} | {row['rate']} | {row['said']} | "
              f"{row['static']} | {row['before']:.3f} | {row['best']:.3f} | {row['ours']:.3f} | "
              f"{row['ours'] / row['best']:.3f} | {row['before_clockless']} |")
    print()
    print('(b) ROS 1 bags, their rosbag2 conversions and CSV: one calibration')
    print('| bag | input | exit | rows | skipped | same as ROS 1 | s | reason |')
    print('|---|---|---:|---:|---:|---|---:|---|')
    bagged = bags()
    for row in bagged:
        print(f"| {row['bag']} | {row['input']} | {row['status']} | {row['rows']} | "
              f"{row['skipped']} | {row['same']} | {row['seconds']:.1f} | {row['reason']} |")

    refused = [row for row in logged if row['said'].startswith('refused')]
    passed = {
        'no refusal at any rate': not refused,
        'ours <= 1.05x best': all(row['ours'] <= TARGET_RATIO * row['best'] for row in logged),
        'one calibration per bag': all(row['same'] for row in bagged),
    }
    print('\ntargets: ' + ', '.join(f"{k} {'PASS' if v else 'FAIL'}" for k, v in passed.items()))
    return 0 if all(passed.values()) and logged and bagged else 1


if __name__ == '__main__':
    sys.exit(main())
