#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Memory of the running nodes: the calibrator, its fit worker and the driver (issue #46).

The simulated driver (100 Hz ``imu/mag``, 225 Hz ``imu/data_raw``) and ``mag_calibrator`` run
as a user starts them, over real DDS in a private ROS_DOMAIN_ID, for ``--duration`` seconds;
the resident set (RSS) and the proportional set (PSS: shared pages split between the processes
that map them, from /proc/PID/smaps_rollup) of each are read at the end, with and without the
IMU (``use_imu``). Beside them, the floor each process's imports alone take (a bare interpreter
importing the same libraries).

    python benchmarks/bench_memory.py               # 60 s each, with and without the IMU
    python benchmarks/bench_memory.py --duration 30
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import random
import signal
import subprocess
import sys
import tempfile
import time

BIN = Path(sys.executable).parent
FLOORS = {
    'numpy': 'import numpy',
    'numpy + scipy.optimize + spatial (the worker with an IMU)':
        'import numpy, scipy.optimize, scipy.spatial.transform',
    'rclpy + the calibrator node module + the WMM (the node)':
        'import mag_calibrator_ros.nodes.mag_calibrator; '
        'from mag_calibrator_ros.calibration.fit.earth_field import import_model; import_model()',
}


def _memory_mb(pid: int) -> tuple[float, float]:
    """(RSS, PSS) in MB of a running process."""
    values = {}
    for line in Path(f'/proc/{pid}/smaps_rollup').read_text().splitlines()[1:]:
        name, _, rest = line.partition(':')
        values[name.strip()] = float(rest.split()[0]) / 1024.0
    return values['Rss'], values['Pss']


def _children(pid: int) -> list[int]:
    try:
        text = Path(f'/proc/{pid}/task/{pid}/children').read_text()
    except OSError:
        return []
    return [int(child) for child in text.split()]


def _floor_mb(code: str) -> float:
    probe = (f'{code}\nfrom pathlib import Path\n'
             "print(Path('/proc/self/status').read_text().split('VmRSS:')[1].split()[0])")
    out = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                         check=True, env={**os.environ, 'ROS_DOMAIN_ID': '0'})
    return float(out.stdout.split()[-1]) / 1024.0


def measure(use_imu: bool, duration_s: float) -> dict[str, tuple[float, float]]:
    env = {**os.environ, 'ROS_DOMAIN_ID': str(random.randint(150, 230)),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    with tempfile.TemporaryDirectory() as tmp:
        driver = subprocess.Popen(
            [BIN / 'icm20948_driver', '--ros-args', '-p', 'backend:=sim',
             '-p', 'sim.motion:=tumble'],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        calibrator = subprocess.Popen(
            [BIN / 'mag_calibrator', '--ros-args', '-p', f'use_imu:={str(use_imu).lower()}',
             '-p', f'calibration_file:={tmp}/calibration.yaml'],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(duration_s)
            found = {'calibrator': _memory_mb(calibrator.pid), 'driver': _memory_mb(driver.pid)}
            for child in _children(calibrator.pid):
                found['worker'] = _memory_mb(child)
        finally:
            for process in (calibrator, driver):
                process.send_signal(signal.SIGINT)
            for process in (calibrator, driver):
                try:
                    process.wait(timeout=15.0)
                except subprocess.TimeoutExpired:
                    process.kill()
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=60.0, help='seconds per run (60)')
    args = parser.parse_args()
    print(f'load average {os.getloadavg()[0]:.2f}')
    for name, code in FLOORS.items():
        print(f'import floor, {name}: {_floor_mb(code):.0f} MB RSS')
    for use_imu in (True, False):
        found = measure(use_imu, args.duration)
        shown = ', '.join(f'{name} {rss:.0f} / {pss:.0f}' for name, (rss, pss) in found.items())
        print(f'use_imu {str(use_imu).lower()} after {args.duration:g} s, MB RSS / PSS: {shown}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
