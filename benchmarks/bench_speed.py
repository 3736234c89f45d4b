# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Speed of the engine, the command line and the nodes (issue #14); ``bench_engine.py --speed``.

(e) fit_calibration time on 300 / 3k / 12k / 2M rows, clean and with 3 % spikes, ``full`` and
    ``auto``, against an algebraic-only fit (normalisation + one quadric least squares: what the
    fastest Python fitters do) as the floor; in process, data loaded, median of repeats. The
    direction error of each (judged on the noise-free readings, as in section (a)) shows what
    the floor's speed costs when the data are not clean.
(f) command line: ``mag_calibrator_fit --help`` and a usage error from a cold interpreter;
    ``--all`` on a 2-million-row CSV, wall time and peak resident memory (ru_maxrss of the
    child, from os.wait4).
(g) nodes: process start to the first message they publish, over real DDS on localhost
    (``icm20948_driver`` with the simulator: ``imu/mag``; ``mag_calibrator`` with a calibration
    file, fed at 100 Hz: ``imu/mag_corrected``), and the import of each node module in a fresh
    interpreter.

Timings are wall-clock on a shared machine: re-run before quoting them.
"""

from __future__ import annotations

from collections.abc import Callable
import math
import os
from pathlib import Path
import random
import resource
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from mag_calibrator_ros.calibration.fit import ellipsoid
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_node import _stop as stop_process  # noqa: E402  (SIGINT, then kill)
from scenarios import (  # noqa: E402
    FIELD_UT,
    NOISE_UT,
    SPIKE_RANGE,
    direction_errors_deg,
    random_hard_iron,
    random_soft_iron,
)

SPEED_ROWS = (300, 3_000, 12_000, 2_000_000)
SPEED_SPIKES = (0.0, 0.03)
BIN = Path(sys.executable).parent
TARGET_12K_MS = {('full', 0.0): 15.0, ('auto', 0.0): 25.0, ('full', 0.03): 60.0,
                 ('auto', 0.03): 60.0}
PROBE_SETTLE_S = 1.0
"""The probe's own DDS participant settles before the first node starts (without it the first
start measured up to 2 s more, all of it discovery)."""
TARGET_HELP_S = 0.25
TARGET_NODE_START_S = 1.0
TARGET_ALL_2M_S = 10.0
TARGET_ALL_2M_MB = 500.0


class Data:
    """Random field directions seen through strong hard and soft iron (section (a)'s 'strong':
    300 µT offset, soft iron up to 0.15 off the diagonal), 0.5 µT noise, optional spikes."""

    def __init__(self, rows: int, spikes: float, seed: int = 0) -> None:
        rng = np.random.default_rng([seed, rows, int(spikes * 1000)])
        truth = rng.normal(size=(rows, 3))
        truth *= FIELD_UT / np.linalg.norm(truth, axis=1, keepdims=True)
        soft, hard = random_soft_iron(rng, 0.10, 0.15), random_hard_iron(rng, 300.0)
        self.truth = truth
        self.reading = truth @ soft.T + hard
        self.raw = self.reading + rng.normal(0.0, NOISE_UT, truth.shape)
        count = int(round(spikes * rows))
        where = rng.choice(rows, size=count, replace=False)
        directions = rng.normal(size=(count, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        self.raw[where] += directions * rng.uniform(*SPIKE_RANGE, (count, 1)) * FIELD_UT

    def direction_rms_deg(self, offset: np.ndarray, matrix: np.ndarray) -> float:
        sample = slice(None, None, max(1, len(self.raw) // 20_000))
        corrected = (self.reading[sample] - offset) @ matrix.T
        return float(np.sqrt(np.mean(direction_errors_deg(corrected, self.truth[sample]) ** 2)))


def algebraic_floor(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Normalisation and one quadric least squares, no robustness, no refinement, no gates."""
    norm = ellipsoid.normalise(raw)
    fitted = ellipsoid.quadric_least_squares(norm.forward(raw))
    if fitted is None:
        return None
    centre, matrix = fitted
    return norm.centre + norm.scale * centre, matrix / norm.scale


def median_ms(call: Callable[[], object], repeats: int) -> float:
    call()  # warm caches
    durations = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        durations.append((time.perf_counter() - start) * 1e3)
    return float(np.median(durations))


def fit_speed(quick: bool) -> tuple[list[list[str]], dict]:
    rows_out, verdicts = [], {}
    for rows in SPEED_ROWS:
        for spikes in SPEED_SPIKES:
            data = Data(rows, spikes)
            repeats = 1 if rows > 100_000 else (5 if quick else 15)
            floor = algebraic_floor(data.raw)
            times = {'floor': median_ms(lambda d=data: algebraic_floor(d.raw), repeats)}
            results = {}
            for model in ('full', 'auto'):
                options = FitOptions(model=model)
                times[model] = median_ms(lambda d=data, o=options: fit_calibration(d.raw, o),
                                         repeats)
                results[model] = fit_calibration(data.raw, options)
                verdicts[(rows, spikes, model)] = times[model]
            path = 'robust' if ellipsoid.fit_ellipsoid(data.raw, 'full').robust else 'fast'
            full = results['full'].calibration
            floor_error = math.nan if floor is None else data.direction_rms_deg(*floor)
            full_error = data.direction_rms_deg(full.offset, full.matrix / full.field_strength)
            rows_out.append([
                f'{rows:,}', f'{100 * spikes:.0f} %', f'{times["floor"]:.1f}',
                f'{times["full"]:.1f}', f'{times["auto"]:.1f}', path,
                results['auto'].metrics.model, f'{floor_error:.3f}', f'{full_error:.3f}',
                str(repeats),
            ])
            print(f'  fit speed: {rows_out[-1]}', file=sys.stderr)
    return rows_out, verdicts


CACHED = {key: value for key, value in os.environ.items() if key != 'PYTHONDONTWRITEBYTECODE'}
"""The environment of an installed package: bytecode written once and read after (with
PYTHONDONTWRITEBYTECODE, as in some CI shells, every start compiles the package anew)."""


def cold_runs(command: list[str], repeats: int, env: dict | None = None) -> tuple[float, float]:
    """(median, min) wall seconds of a fresh process (after one untimed run)."""
    durations = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False,
                       env=env)
        durations.append(time.perf_counter() - start)
    return float(np.median(durations[1:])), float(min(durations[1:]))


def run_measured(command: list[str]) -> tuple[float, float, int]:
    """(wall seconds, peak resident MB, exit status) of one child process.

    ru_maxrss of a child includes what its parent held when it forked (the high-water mark
    survives fork and exec on Linux), so this runs before anything big is allocated here.
    """
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env=CACHED)
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    return time.perf_counter() - start, usage.ru_maxrss / 1024.0, process.returncode


def cli_speed(quick: bool) -> tuple[list[list[str]], dict]:
    fit = str(BIN / 'mag_calibrator_fit')
    repeats = 5 if quick else 15
    rows_out, verdicts = [], {}
    median, fastest = cold_runs([fit, '--help'], repeats, CACHED)
    verdicts['help'] = median
    rows_out.append(['mag_calibrator_fit --help', f'{median:.3f} s (min {fastest:.3f})', '—',
                     str(repeats)])
    median, fastest = cold_runs([fit, '--model', 'nope', 'x.txt'], repeats, CACHED)
    rows_out.append(['usage error (exit 2)', f'{median:.3f} s (min {fastest:.3f})', '—',
                     str(repeats)])
    if 'PYTHONDONTWRITEBYTECODE' in os.environ:
        median, fastest = cold_runs([fit, '--help'], repeats)
        rows_out.append(['--help, PYTHONDONTWRITEBYTECODE set (package compiled every start)',
                         f'{median:.3f} s (min {fastest:.3f})', '—', str(repeats)])
    median, fastest = cold_runs([sys.executable, '-c', 'pass'], repeats)
    rows_out.append(['(python -c pass: the interpreter alone)',
                     f'{median:.3f} s (min {fastest:.3f})', '—', str(repeats)])
    if quick:
        return rows_out, verdicts
    with tempfile.TemporaryDirectory() as directory:
        for spikes in SPEED_SPIKES:
            path = Path(directory) / f'two_million_{int(100 * spikes)}.csv'
            subprocess.run([sys.executable, __file__, '--write-csv', str(path), str(spikes)],
                           check=True)  # in a child: this process stays small (run_measured)
            seconds, megabytes, code = run_measured([fit, str(path), '--all', '--json'])
            verdicts[('all', spikes)] = (seconds, megabytes, code)
            rows_out.append([f'--all, 2,000,000 rows, {100 * spikes:.0f} % spikes (exit {code})',
                             f'{seconds:.2f} s', f'{megabytes:.0f}', '1'])
            print(f'  cli: {rows_out[-1]}', file=sys.stderr)
    return rows_out, verdicts


# -- (g) nodes --


class _Probe:
    """One rclpy node in this process: feeds imu/mag at 100 Hz and notes when the first message
    arrives on a topic."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import MagneticField

        self._rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node('bench_speed_probe')
        self._message_type = MagneticField
        self._qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
        self._first: dict[str, float] = {}
        self._lock = threading.Lock()
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self._publisher = self.node.create_publisher(MagneticField, 'imu/mag', reliable)
        self.feeding = False
        self.node.create_timer(0.01, self._feed)
        for topic in ('imu/mag', 'imu/mag_corrected'):
            self.node.create_subscription(MagneticField, topic,
                                          lambda _, t=topic: self._arrived(t), self._qos)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()
        time.sleep(PROBE_SETTLE_S)

    def _feed(self) -> None:
        if self.feeding:
            message = self._message_type()
            message.header.frame_id = 'imu_link'
            message.magnetic_field.x, message.magnetic_field.y = 20e-6, -5e-6
            message.magnetic_field.z = 40e-6
            self._publisher.publish(message)

    def _arrived(self, topic: str) -> None:
        now = time.perf_counter()
        with self._lock:
            self._first.setdefault(topic, now)

    def reset(self) -> None:
        with self._lock:
            self._first.clear()

    def first(self, topic: str) -> float | None:
        with self._lock:
            return self._first.get(topic)

    def close(self) -> None:
        self._executor.shutdown(timeout_sec=2.0)
        self._thread.join(timeout=5.0)
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def _start_to_first(probe: _Probe, command: list[str], topic: str, feed: bool) -> float:
    probe.reset()
    probe.feeding = feed
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env=CACHED)
    try:
        deadline = start + 30.0
        while probe.first(topic) is None:
            if process.poll() is not None or time.perf_counter() > deadline:
                return math.nan
            time.sleep(0.002)
        return probe.first(topic) - start
    finally:
        probe.feeding = False
        stop_process(process)
        time.sleep(0.3)  # let the topic's last messages drain before the next start


BARE_PUBLISHER = """
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import MagneticField

rclpy.init()
node = rclpy.create_node('bare_publisher')
publisher = node.create_publisher(MagneticField, 'imu/mag', QoSProfile(
    depth=10, reliability=ReliabilityPolicy.RELIABLE))
node.create_timer(0.01, lambda: publisher.publish(MagneticField()))
try:
    rclpy.spin(node)
except BaseException:
    pass
"""


def node_speed(quick: bool) -> tuple[list[list[str]], dict]:
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(150, 200)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    repeats = 2 if quick else 7
    rows_out, verdicts = [], {}
    for module in ('icm20948_driver', 'mag_calibrator'):
        median, fastest = cold_runs(
            [sys.executable, '-c', f'import mag_calibrator_ros.nodes.{module}'], repeats, CACHED)
        rows_out.append([f'import mag_calibrator_ros.nodes.{module}',
                         f'{median:.3f} s (min {fastest:.3f})', str(repeats)])
    probe = _Probe()
    try:
        with tempfile.TemporaryDirectory() as directory:
            from mag_calibrator_ros.calibration import Calibration
            from mag_calibrator_ros.calibration.store.calibration_file import save_calibration

            calibration_file = Path(directory) / 'calibration.yaml'
            save_calibration(calibration_file, Calibration(np.zeros(3), np.eye(3), 50e-6))
            bare = Path(directory) / 'bare_publisher.py'
            bare.write_text(BARE_PUBLISHER)
            cases = {
                'bare rclpy publisher (the floor: interpreter, rclpy, discovery) -> imu/mag': (
                    [sys.executable, str(bare)], 'imu/mag', False),
                'icm20948_driver (sim) -> first imu/mag': (
                    [str(BIN / 'icm20948_driver'), '--ros-args', '-p', 'backend:=sim',
                     '--log-level', 'warn'], 'imu/mag', False),
                'mag_calibrator (calibration file, fed 100 Hz) -> first imu/mag_corrected': (
                    [str(BIN / 'mag_calibrator'), '--ros-args', '-p',
                     f'calibration_file:={calibration_file}', '-p', 'auto_calibrate:=false',
                     '--log-level', 'warn'], 'imu/mag_corrected', True),
            }
            for name, (command, topic, feed) in cases.items():
                if name.startswith('bare'):
                    times = [_start_to_first(probe, command, topic, feed) for _ in range(repeats)]
                    rows_out.append([name, f'{np.nanmedian(times):.3f} s (min '
                                     f'{np.nanmin(times):.3f})', str(repeats)])
                    continue
                times = [_start_to_first(probe, command, topic, feed) for _ in range(repeats)]
                verdicts[name] = float(np.nanmedian(times)) if not np.all(np.isnan(times)) \
                    else math.nan
                rows_out.append([name, f'{verdicts[name]:.3f} s (min {np.nanmin(times):.3f})',
                                 str(repeats)])
                print(f'  node: {rows_out[-1]}', file=sys.stderr)
    finally:
        probe.close()
    return rows_out, verdicts


def speed_main(quick: bool, markdown: bool, print_table: Callable, table_type: type) -> int:
    """Run sections (e)-(g) and print them with bench_engine's table printer."""
    started = time.perf_counter()
    cli_rows, cli_verdicts = cli_speed(quick)  # first: its memory figures need a small parent
    fit_rows, fit_verdicts = fit_speed(quick)
    table = table_type(
        '(e) fit_calibration time, ms (median), and direction error RMS of the result, degrees',
        ['rows', 'spikes', 'floor ms', 'full ms', 'auto ms', 'full path', 'auto model',
         'floor err °', 'full err °', 'repeats'], fit_rows)
    table.notes = [
        'floor = normalisation + one quadric least squares (no robustness, refinement or gates); '
        'full/auto = fit_calibration with every gate and the coverage; full path = fast '
        '(algebraic start, inliers fitted at once) or robust (trimmed start, soft-L1)',
        'data: random directions, 50 µT, 300 µT hard iron, soft iron up to 0.15 off the '
        'diagonal, 0.5 µT noise, spikes of 0.3-2 F; errors judged on the noise-free readings',
    ]
    print_table(table, markdown)
    table = table_type('(f) command line, cold start', ['run', 'wall', 'peak RSS MB', 'runs'],
                       cli_rows)
    table.notes = ['cold = a new process with bytecode cached (as installed), median after one '
                   'untimed run; peak RSS of the child process (os.wait4 ru_maxrss); the '
                   '2M-row CSV has a mx,my,mz header and 5 decimals']
    print_table(table, markdown)
    node_rows, node_verdicts = node_speed(quick)
    table = table_type('(g) nodes: process start to first published message',
                       ['run', 'wall', 'runs'], node_rows)
    table.notes = [f'real DDS on localhost, ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID")}; '
                   'includes the interpreter, imports, rclpy init, parameters and discovery, '
                   'which alone varies from run to run here (0.4 s or 2.5 s for the bare '
                   'publisher): compare each node with that floor']
    print_table(table, markdown)

    lines = []

    def verdict(ok: bool, text: str) -> None:
        lines.append(f'{"PASS" if ok else "FAIL"}  {text}')

    for (model, spikes), limit in TARGET_12K_MS.items():
        value = fit_verdicts[(12_000, spikes, model)]
        verdict(value <= limit, f'12k rows, {100 * spikes:.0f} % spikes, {model}: '
                                f'{value:.1f} ms <= {limit:.0f} ms')
    verdict(cli_verdicts['help'] <= TARGET_HELP_S,
            f'mag_calibrator_fit --help: {cli_verdicts["help"]:.3f} s <= {TARGET_HELP_S} s')
    for name, value in node_verdicts.items():
        verdict(value <= TARGET_NODE_START_S, f'{name}: {value:.2f} s <= {TARGET_NODE_START_S} s')
    for spikes in SPEED_SPIKES:
        if ('all', spikes) in cli_verdicts:
            seconds, megabytes, code = cli_verdicts[('all', spikes)]
            verdict(seconds <= TARGET_ALL_2M_S and megabytes <= TARGET_ALL_2M_MB and code == 0,
                    f'--all on 2M rows, {100 * spikes:.0f} % spikes: {seconds:.1f} s <= '
                    f'{TARGET_ALL_2M_S:.0f} s, {megabytes:.0f} MB <= {TARGET_ALL_2M_MB:.0f} MB')
    print('\n#### Targets (issue #14)\n' if markdown else '\nTargets (issue #14)')
    for line in lines:
        print(f'- {line}' if markdown else f'  {line}')
    print(f'\n(run time {time.perf_counter() - started:.0f} s{", --quick" if quick else ""}; '
          f'peak RSS of this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss >> 10} '
          'MB)')
    return 0


def write_csv(path: str, spikes: float) -> None:
    """The 2M-row CSV of section (f): mx,my,mz header, 5 decimals."""
    np.savetxt(path, Data(2_000_000, spikes, seed=1).raw, fmt='%.5f', delimiter=',',
               header='mx,my,mz', comments='')


if __name__ == '__main__':
    if len(sys.argv) == 4 and sys.argv[1] == '--write-csv':
        write_csv(sys.argv[2], float(sys.argv[3]))
    else:
        sys.exit('run: python benchmarks/bench_engine.py --speed')
