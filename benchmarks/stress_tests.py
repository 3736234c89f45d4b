#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Run tests again and again while other processes keep every core busy, and say which failed.

A node test that passes on a quiet computer can fail on a loaded one (a robot's computer is
loaded): DDS delivery, executors and the fit worker all slow down and interleave differently.
This runs the chosen tests (``make test``, or pytest on the given files) ``--runs`` times in a
row with ``--busy`` pure-Python busy loops at normal priority (one per core by default), and
prints one line per run: pass or fail, its duration and the failed tests' names. A failure it
finds is a defect to understand, not a run to repeat.

    python benchmarks/stress_tests.py --runs 5 test/test_ground_node.py test/test_driver_node.py
    python benchmarks/stress_tests.py --runs 20 --make        # make test, 20 times
    python benchmarks/stress_tests.py --runs 3 --busy 0 test/test_launch.py   # no extra load
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

ROOT = Path(__file__).resolve().parent.parent
FAILED = re.compile(r'^(?:FAILED|ERROR) (\S+)', re.MULTILINE)
SUMMARY = re.compile(r'^=*\s*(\d+ (?:passed|failed).*?)\s*=*$', re.MULTILINE)


def _spin() -> None:
    """One core's worth of work that never sleeps (the load a busy robot computer puts on)."""
    value = 0
    while True:
        value = (value * 1103515245 + 12345) & 0x7FFFFFFF


def start_load(count: int) -> list[multiprocessing.Process]:
    """``count`` busy loops in daemon processes (they end with this one)."""
    loops = []
    for _ in range(count):
        loop = multiprocessing.Process(target=_spin, daemon=True)
        loop.start()
        loops.append(loop)
    return loops


def stop_load(loops: list[multiprocessing.Process]) -> None:
    for loop in loops:
        loop.terminate()
    for loop in loops:
        loop.join(timeout=5.0)


def command(args: argparse.Namespace) -> list[str]:
    """What one run executes: ``make test`` or pytest on the files, this checkout first."""
    if args.make:
        return ['make', 'test'] + ([f'VENV={args.venv}'] if args.venv else [])
    return [sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', '-rfE',
            '-n', 'auto', '--dist', 'loadfile', *args.tests]  # as make test runs them


def run_once(cmd: list[str], timeout_s: float) -> dict:
    """One run: exit code, seconds, failed test ids and pytest's summary line."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    start = time.monotonic()
    # its own session, so its nodes and workers can be ended as one group, and are (a timeout,
    # Ctrl-C or SIGTERM of this runner)
    child = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, start_new_session=True)
    output = ''
    try:
        output, _ = child.communicate(timeout=timeout_s)
        code = child.returncode
    except subprocess.TimeoutExpired:
        code, output = 'timeout', ''
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
            leftover, _ = child.communicate()
            output += leftover or ''
    seconds = time.monotonic() - start
    summary = SUMMARY.findall(output)
    return {'code': code, 'seconds': round(seconds, 1), 'failed': FAILED.findall(output),
            'summary': summary[-1] if summary else '', 'output': output}


def load_average() -> str:
    try:
        return ' '.join(f'{value:.1f}' for value in os.getloadavg())
    except OSError:
        return '?'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('tests', nargs='*', default=['test'],
                        help='test files or directories for pytest (default: test)')
    parser.add_argument('--runs', type=int, default=5, help='runs in a row (default 5)')
    parser.add_argument('--busy', type=int, default=os.cpu_count() or 1,
                        help='busy-loop processes kept running (default: one per core)')
    parser.add_argument('--make', action='store_true', help='run `make test` instead of pytest')
    parser.add_argument('--venv', help="VENV for make (default: the Makefile's)")
    parser.add_argument('--timeout', type=float, default=3600.0, help='seconds per run')
    parser.add_argument('--logs', type=Path,
                        help="directory to write each failed run's full output into")
    parser.add_argument('--json', type=Path, help='write the per-run results here')
    args = parser.parse_args(argv)
    if args.runs < 1 or args.busy < 0:
        parser.error('--runs must be at least 1 and --busy at least 0')
    cmd = command(args)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # ends the run's group too
    print(f'# {" ".join(cmd)}  x{args.runs}, {args.busy} busy loop(s), '
          f'{os.cpu_count()} core(s)', flush=True)
    loops = start_load(args.busy)
    results = []
    try:
        for run in range(1, args.runs + 1):
            result = run_once(cmd, args.timeout)
            result['load'] = load_average()
            verdict = 'pass' if result['code'] == 0 else f'FAIL ({result["code"]})'
            print(f'run {run}: {verdict}, {result["seconds"]} s, load {result["load"]}, '
                  f'{result["summary"]}', flush=True)
            for test in result['failed']:
                print(f'    {test}', flush=True)
            if result['code'] != 0 and args.logs is not None:
                args.logs.mkdir(parents=True, exist_ok=True)
                (args.logs / f'run{run}.log').write_text(result['output'])
            results.append({key: value for key, value in result.items() if key != 'output'})
    except (KeyboardInterrupt, SystemExit):
        print(f'# interrupted after {len(results)} run(s)', flush=True)
        return 130
    finally:
        stop_load(loops)
    passed = sum(result['code'] == 0 for result in results)
    print(f'# {passed} of {len(results)} runs passed', flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps({'command': cmd, 'busy': args.busy,
                                         'runs': results}, indent=1))
    return 0 if passed == len(results) else 1


if __name__ == '__main__':
    sys.exit(main())
