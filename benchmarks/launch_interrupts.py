#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Ctrl-C of ``ros2 launch``, as a terminal sends it, N times: does every launch end cleanly?

Each run starts ``ros2 launch mag_calibrator_ros mag_calibrator.launch.py backend:=sim
namespace:=<ns>`` in a process group of its own (a terminal's foreground job), waits until both
nodes have logged that they run (plus a random extra moment, so the signal also lands at
different points of their work), then sends SIGINT to the whole group, as Ctrl-C does: every
node gets it from the "terminal" and once more from launch, which forwards it. A run is clean
when launch exits 0 within the timeout, no process printed a traceback and launch reported no
process as died. Needs the package built and sourced (colcon), and ``ros2`` on the PATH.
With ``--signal SIGTERM`` launch itself dies at once with -15 and leaves its nodes to the
group's signal (ros2/launch#666): that mode shows launch's behaviour, not the nodes'.

    python benchmarks/launch_interrupts.py --runs 20
    python benchmarks/launch_interrupts.py --runs 5 --extra-arguments sim.motion:=yaw
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time

READY_MARKERS = ('sim backend, ICM-20948', '[mag_calibrator-2]')
"""The driver's start-up line, and the calibrator's first line (any: it has started)."""
READY_TIMEOUT_S = 60.0
EXIT_TIMEOUT_S = 30.0
FAILURE_MARKERS = ('Traceback', 'process has died', 'KeyboardInterrupt')


def one_run(index: int, arguments: list[str], stop_signal: signal.Signals, extra_wait_s: float,
            log_directory: str) -> tuple[bool, str]:
    """(clean, a one-line verdict) of one launch stopped by ``stop_signal`` to its group."""
    log_path = os.path.join(log_directory, f'launch_{index:02d}.log')
    with open(log_path, 'w+b') as log:
        process = subprocess.Popen(
            ['ros2', 'launch', 'mag_calibrator_ros', 'mag_calibrator.launch.py', *arguments],
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True)
        group = process.pid
        ready_since = None
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline and process.poll() is None:
            text = _read(log_path)
            if all(marker in text for marker in READY_MARKERS):
                ready_since = time.monotonic()
                break
            time.sleep(0.1)
        if ready_since is None:
            _kill(group, process)
            return False, f'never ready (see {log_path})'
        time.sleep(extra_wait_s)
        os.killpg(group, stop_signal)
        hung = False
        try:
            code = process.wait(timeout=EXIT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            hung = True
            _kill(group, process)
            code = process.returncode
        time.sleep(0.2)  # children's last lines
        text = _read(log_path)
    failures = [marker for marker in FAILURE_MARKERS if marker in text]
    clean = not hung and code == 0 and not failures
    verdict = ('clean' if clean else
               f"{'HUNG, ' if hung else ''}exit {code}, {', '.join(failures) or 'no marker'} "
               f'(see {log_path})')
    return clean, verdict


def _read(path: str) -> str:
    with open(path, 'rb') as handle:
        return handle.read().decode(errors='replace')


def _kill(group: int, process: subprocess.Popen) -> None:
    try:
        os.killpg(group, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=20)
    parser.add_argument('--signal', default='SIGINT', choices=('SIGINT', 'SIGTERM'))
    parser.add_argument('--namespace', default='robot1')
    parser.add_argument('--max-extra-wait', type=float, default=2.0,
                        help='seconds of random extra wait after both nodes are up')
    parser.add_argument('--extra-arguments', nargs='*', default=[],
                        help='more launch arguments, name:=value')
    parser.add_argument('--seed', type=int, default=1)
    options = parser.parse_args()
    # A private domain on localhost, so the runs never meet another ROS graph.
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(150, 230)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_HOME', tempfile.mkdtemp(prefix='launch_interrupts_ros_home_'))
    rng = random.Random(options.seed)
    log_directory = tempfile.mkdtemp(prefix='launch_interrupts_')
    arguments = ['backend:=sim', f'namespace:={options.namespace}', *options.extra_arguments]
    clean = 0
    for index in range(options.runs):
        ok, verdict = one_run(index, arguments, signal.Signals[options.signal],
                              rng.uniform(0.0, options.max_extra_wait), log_directory)
        clean += ok
        print(f'run {index + 1:2d}: {verdict}', flush=True)
    print(f'{clean} of {options.runs} clean exits ({options.signal} to the launch process group; '
          f'logs in {log_directory})')
    return 0 if clean == options.runs else 1


if __name__ == '__main__':
    sys.exit(main())
