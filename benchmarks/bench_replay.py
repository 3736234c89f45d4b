#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The live calibrator on recordings it never saw: replayed through the node over real DDS.

(a) Every shared recording, and a synthetic tumble, published message by message on ``imu/mag``
    (stamped at --rate, 100 Hz) to a ``mag_calibrator`` node with its defaults (auto_calibrate and
    refine on, no service call), three passes each. Reported: the magnitude spread (std/mean of
    |corrected|) of what the node published in the last pass, against the spread of a fit of
    every row of the recording; the message at which the first corrected message came out; the
    message at which the node counted itself converged.
(b) The wrong file: the simulated ICM-20948 tumbling, the calibrator started with another
    board's calibration. Seconds from the first message until the node warns that the
    calibration does not fit, and until it has recalibrated by itself.

    python benchmarks/bench_replay.py --data ../shared/data
    python benchmarks/bench_replay.py --data ../shared/data --speed 10   # same decisions, faster
    python benchmarks/bench_replay.py --data ../shared/data --only fxos8700 --passes 10
    python benchmarks/bench_replay.py --data ../shared/data --passes 10 --fresh-noise 0.003
    python benchmarks/bench_replay.py --data ../shared/data --passes 10 --offline

After the last pass the node is asked for ``~/calibrate``: "calibrate" is the spread of the last
pass under what is in force after its answer (the live one when the fit fails its gates: what a
user calling it would have), so "live - calibrate" says how far the adoption rule stopped short
of what the node itself could give. ``--fresh-noise F`` adds new Gaussian noise of F times |raw|
per axis to every pass (a replay otherwise repeats the same readings, so readings held out in a
later pass are copies of readings the buffer holds); the all-rows fit is then of the last pass's
rows. ``--offline`` streams the same messages through ``CalibrationSession`` with the inline
runner, as ``mag_calibrator_fit`` and ``benchmarks/decision_log.py`` do (the node's decisions
on the same stamps, minutes faster, no DDS); section (b) needs the node and is skipped.

Stream time comes from the message stamps, so --speed (publishing faster than the stamps say)
changes no decision of the node: only how long the benchmark takes. Recordings in µT or counts
are scaled to an Earth-like field in tesla (the node names any other unit as wrong; the engine's
decisions do not depend on a common scale) and replayed with the saturation check off.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import os
from pathlib import Path
import random
import sys
import tempfile
import threading
import time

import numpy as np

os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(101, 149)))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import MagneticField  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from mag_calibrator_ros.calibration.fit.calibration import Calibration  # noqa: E402
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration  # noqa: E402
from mag_calibrator_ros.calibration.fit.robust import mad_sigma  # noqa: E402
from mag_calibrator_ros.calibration.live.offline import calibrate_now  # noqa: E402
from mag_calibrator_ros.calibration.live.session import CalibrationSession  # noqa: E402
from mag_calibrator_ros.calibration.live.settings import SessionSettings  # noqa: E402
from mag_calibrator_ros.calibration.store.calibration_file import save_calibration  # noqa: E402
from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode  # noqa: E402
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode  # noqa: E402
from mag_calibrator_ros.nodes.runtime import NodeThreads  # noqa: E402
from mag_calibrator_ros.sim import motion  # noqa: E402
from mag_calibrator_ros.tools.recordings import read_recording  # noqa: E402

TARGET_SPREAD_RATIO = 1.03
TARGET_OVER_CALIBRATE = 0.02
"""Issue #25: the live ratio at most the ~/calibrate-at-the-end ratio + 0.02."""
WARN_TARGET_S = 10.0
RECALIBRATED_TARGET_S = 30.0


def as_tesla(rows: np.ndarray) -> np.ndarray:
    """The rows scaled so their median |raw| is 50 µT, as tesla: what a driver in µT or counts
    would publish once converted (every spread and ratio here is relative, so unchanged)."""
    return rows * (50e-6 / float(np.median(np.linalg.norm(rows, axis=1))))


@dataclass(frozen=True)
class Replay:
    name: str
    path: str | None  # under --data; None: synthetic
    columns: str | None = None


REPLAYS = (
    Replay('gd-notebook long', 'gd-notebook/mag_raw_data_long.txt'),
    Replay('gd-notebook short', 'gd-notebook/mag_raw_data.txt'),
    Replay('gd deployment 1', 'gd-notebook/deployment/validation_data_step1en1.txt', '3,4,5'),
    Replay('gd deployment 2', 'gd-notebook/deployment/validation_data_step1en2.txt', '3,4,5'),
    Replay('gd deployment 3', 'gd-notebook/deployment/validation_data_step1en3.txt', '3,4,5'),
    Replay('fxos8700', 'fxos8700-mwrona/mag-readings.txt'),
    Replay('bno055', 'bno055-jremington/bno055_mag.csv'),
    Replay('lsm303dlhc', 'lsm303dlhc-altimu10v3/mag_2.txt'),
    Replay('lsm303dlhc log', 'lsm303dlhc-altimu10v3/cal_output_2.log', '3,4,5'),
    Replay('synthetic tumble', None),
)


def synthetic_rows(n: int = 3000) -> np.ndarray:
    """A hand tumble at 100 Hz in tesla: 120 uT hard iron, strong soft iron, 0.3 uT noise."""
    truth = motion.body_field_samples('tumble', n, 100.0, 50e-6, 60.0, seed=11)
    soft = np.array([[1.15, 0.10, -0.08], [0.10, 0.85, 0.12], [-0.08, 0.12, 1.00]])
    raw = truth @ soft.T + np.array([120e-6, -80e-6, 60e-6])
    return raw + np.random.default_rng(11).normal(0.0, 0.3e-6, raw.shape)


def passes_of(rows: np.ndarray, passes: int, fresh_noise: float, seed: int) -> list[np.ndarray]:
    """The rows of every pass: the same rows, or with new noise of ``fresh_noise`` x |raw| per
    axis in each pass (seeded: the same benchmark run twice feeds the same readings)."""
    if fresh_noise <= 0.0:
        return [rows] * passes
    rng = np.random.default_rng(seed)
    scale = fresh_noise * np.linalg.norm(rows, axis=1, keepdims=True)
    return [rows + rng.normal(0.0, 1.0, rows.shape) * scale for _ in range(passes)]


def spread_pct(corrected: np.ndarray) -> float:
    magnitudes = np.linalg.norm(corrected, axis=1)
    return float(100.0 * magnitudes.std() / magnitudes.mean()) if len(magnitudes) else np.nan


def robust_spread_pct(corrected: np.ndarray) -> float:
    """1.4826 MAD / median of |corrected|: the spread of the undisturbed readings, which a few
    disturbed ones (a magnet, a spike) do not move: what the node's own judgements weigh."""
    magnitudes = np.linalg.norm(corrected, axis=1)
    if not len(magnitudes):
        return np.nan
    median = float(np.median(magnitudes))
    return 100.0 * mad_sigma(magnitudes) / median


class Feeder(Node):
    """Publishes rows on imu/mag and records what comes back on imu/mag_corrected."""

    def __init__(self, context: Context, namespace: str) -> None:
        super().__init__('replay_feeder', namespace=namespace, context=context)
        reliable = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        self.publisher = self.create_publisher(MagneticField, 'imu/mag', reliable)
        self.create_subscription(MagneticField, 'imu/mag_corrected', self._on_corrected, 1000)
        self.calibrate = self.create_client(Trigger, 'mag_calibrator/calibrate')
        self._lock = threading.Lock()
        self.corrected: dict[int, np.ndarray] = {}  # message index -> corrected field

    def _on_corrected(self, msg: MagneticField) -> None:
        index = (msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) // self.step_ns
        with self._lock:
            self.corrected[int(index)] = np.array(
                [msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z])

    def play(self, passes: list[np.ndarray], rate: float, speed: float,
             on_message=None) -> None:
        self.step_ns = int(round(1e9 / rate))
        message = MagneticField()
        message.header.frame_id = 'imu_link'
        period = 1.0 / (rate * speed)
        next_send = time.perf_counter()
        index = 0
        for rows in passes:
            for row in rows:
                now = time.perf_counter()
                if now < next_send:
                    time.sleep(next_send - now)
                next_send += period
                message.header.stamp.sec, message.header.stamp.nanosec = divmod(
                    index * self.step_ns, 10**9)
                message.magnetic_field.x, message.magnetic_field.y, message.magnetic_field.z = (
                    float(v) for v in row)
                self.publisher.publish(message)
                if on_message is not None:
                    on_message(index)
                index += 1


def wait(condition, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def replay(threads: NodeThreads, context: Context, directory: Path, number: int, spec: Replay,
           passes: list[np.ndarray], args: argparse.Namespace) -> dict:
    namespace = f'replay{number}'
    overrides = [Parameter('calibration_file', value=str(directory / f'{namespace}.yaml')),
                 Parameter('progress_log_period', value=0.0)]
    if spec.path is not None:
        overrides.append(Parameter('full_scale', value=0.0))
    node = threads.add(MagCalibratorNode(namespace=namespace, context=context,
                                         parameter_overrides=overrides))
    feeder = threads.add(Feeder(context, namespace))
    assert wait(lambda: feeder.publisher.get_subscription_count() >= 1
                and feeder.count_publishers(f'/{namespace}/imu/mag_corrected') >= 1, 30.0)
    time.sleep(0.5)
    converged: list[int] = []

    def watch(index: int) -> None:
        if not converged and node.session.calibration is not None \
                and node.session.report().state == 'calibrated-converged':
            converged.append(index)

    rows = passes[-1]
    total = len(rows) * len(passes)
    feeder.play(passes, args.rate, args.speed, watch)
    wait(lambda: len(feeder.corrected) >= total - 5, 5.0)
    time.sleep(0.5)
    with feeder._lock:
        corrected = dict(feeder.corrected)
    session = node.session
    report = session.report()
    result = {
        'rows': len(rows),
        'first': min(corrected) if corrected else None,
        'converged': converged[0] if converged else None,
        'received': len(corrected),
        'adoptions': dict(report.counts.adoptions),
        'state': report.state,
    }
    last_pass = np.array([corrected[i] for i in range(total - len(rows), total)
                          if i in corrected])
    result['live_spread'] = spread_pct(last_pass) if len(last_pass) else np.nan
    result['live_robust'] = robust_spread_pct(last_pass) if len(last_pass) else np.nan
    result['last_pass_outputs'] = len(last_pass)
    result['calibrate_spread'] = np.nan
    if feeder.calibrate.wait_for_service(timeout_sec=10.0):
        future = feeder.calibrate.call_async(Trigger.Request())
        if wait(future.done, 120.0) and session.calibration is not None:
            result['calibrate_spread'] = spread_pct(session.calibration.apply(rows))
            result['calibrate_failed'] = not future.result().success
    threads.remove(feeder)
    threads.remove(node)
    return result


def offline_replay(spec: Replay, passes: list[np.ndarray], args: argparse.Namespace) -> dict:
    """The same messages through ``CalibrationSession`` with the inline runner (the node's
    defaults, a poll every 50 messages as its timer interleaves): the same decisions."""
    settings = SessionSettings(full_scale=0.0) if spec.path is not None else SessionSettings()
    session = CalibrationSession(settings)
    step_ns = int(round(1e9 / args.rate))
    rows = passes[-1]
    total = len(rows) * len(passes)
    first = converged = None
    last_pass = []
    index = 0
    for pass_rows in passes:
        for row in pass_rows.tolist():
            out = session.process(index * step_ns, 'imu_link', row)
            if out.corrected is not None:
                first = index if first is None else first
                if index >= total - len(rows):
                    last_pass.append(out.corrected)
            index += 1
            if index % 50 == 0:
                session.poll()
            if converged is None and session.calibration is not None \
                    and session.report().state == 'calibrated-converged':
                converged = index
            session.take_events()
    live = np.array(last_pass)
    adoptions = dict(session.report().counts.adoptions)
    attempt = calibrate_now(session)
    result = {
        'rows': len(rows), 'first': first, 'converged': converged, 'received': index,
        'adoptions': adoptions,
        'state': session.report().state,
        'live_spread': spread_pct(live) if len(live) else np.nan,
        'live_robust': robust_spread_pct(live) if len(live) else np.nan,
        'calibrate_spread': (spread_pct(session.calibration.apply(rows))
                             if session.calibration is not None else np.nan),
        'calibrate_failed': not attempt.success,
    }
    session.close()
    return result


def all_rows_fit(rows: np.ndarray) -> tuple[float, float, bool]:
    """A fit of every row: its spread, its robust spread and whether it passed its own gates."""
    result = fit_calibration(rows, FitOptions())
    corrected = result.calibration.apply(rows)
    return spread_pct(corrected), robust_spread_pct(corrected), result.success


def recordings_section(threads, context, directory, args) -> tuple[list[list[str]], bool]:
    table, passed = [], True
    for number, spec in enumerate(REPLAYS):
        if args.only and not any(name in spec.name for name in args.only):
            continue
        if spec.path is None:
            rows = synthetic_rows()
        else:
            rows = as_tesla(read_recording(args.data / spec.path, columns=spec.columns).samples)
        passes = passes_of(rows, args.passes, args.fresh_noise, seed=number)
        reference, robust_reference, gates_passed = all_rows_fit(passes[-1])
        if args.offline:
            result = offline_replay(spec, passes, args)
        else:
            result = replay(threads, context, directory, number, spec, passes, args)
        ratio = result['live_spread'] / reference
        robust_ratio = result['live_robust'] / robust_reference
        calibrate_ratio = result['calibrate_spread'] / reference
        ok = bool(ratio <= calibrate_ratio + TARGET_OVER_CALIBRATE)
        passed &= ok
        adoptions = ', '.join(f'{k} {v}' for k, v in sorted(result['adoptions'].items()))
        table.append([
            spec.name, str(result['rows']), f"{result['received']}/{len(rows) * args.passes}",
            f"{reference:.3f}{'' if gates_passed else '*'}", f"{result['live_spread']:.3f}",
            f'{ratio:.3f}', f'{robust_ratio:.3f}',
            f"{calibrate_ratio:.3f}{'†' if result.get('calibrate_failed') else ''}",
            'PASS' if ok else 'FAIL', str(result['first']), str(result['converged']),
            adoptions or '-', result['state'],
        ])
        print(f"  {spec.name}: live {result['live_spread']:.3f} % vs all rows {reference:.3f} %"
              f' ({ratio:.3f}x, ~/calibrate {calibrate_ratio:.3f}x), first corrected message '
              f"{result['first']}, converged at {result['converged']}, {adoptions}",
              file=sys.stderr)
    return table, passed


def wrong_file_section(threads, context, directory, args) -> tuple[list[list[str]], bool]:
    """The sim tumbling at 100 Hz; the calibrator starts with another board's calibration."""
    table, passed = [], True
    other = Calibration(np.array([260e-6, -140e-6, 80e-6]), np.diag([0.9, 1.1, 1.0]), 50e-6,
                        'full', {'residual_rms_pct': 0.5, 'coverage': 0.9})
    for seed in range(args.wrong_file_runs):
        namespace = f'wrong{seed}'
        path = directory / f'{namespace}.yaml'
        save_calibration(path, other, node_name='/**')
        driver = threads.add(Icm20948DriverNode(namespace=namespace, context=context,
                                                parameter_overrides=[
            Parameter('backend', value='sim'), Parameter('rate_hz', value=100),
            Parameter('sim.motion', value='tumble'), Parameter('sim.seed', value=seed),
            Parameter('sim.hard_iron_ut', value=[120.0, -80.0, 60.0]),
            Parameter('sim.soft_iron', value=[1.15, 0.10, -0.08, 0.10, 0.85, 0.12, -0.08, 0.12,
                                              1.00])]))
        started = time.monotonic()
        node = threads.add(MagCalibratorNode(namespace=namespace, context=context,
                                             parameter_overrides=[
            Parameter('calibration_file', value=str(path)),
            Parameter('progress_log_period', value=0.0)]))
        wait(lambda calibrator=node: calibrator.session.report().counts.accepted > 0, 30.0)
        first = time.monotonic()
        warned = recalibrated = None
        deadline = first + 90.0
        while time.monotonic() < deadline and recalibrated is None:
            report = node.session.report()
            if warned is None and report.state == 'calibrated-misfit':
                warned = time.monotonic() - first
            if report.counts.adoptions.get('auto'):
                recalibrated = time.monotonic() - first
            time.sleep(0.02)
        ok = (warned is not None and warned <= WARN_TARGET_S and recalibrated is not None
              and recalibrated <= RECALIBRATED_TARGET_S)
        passed &= ok
        table.append([str(seed), f'{first - started:.1f}',
                      '-' if warned is None else f'{warned:.1f}',
                      '-' if recalibrated is None else f'{recalibrated:.1f}',
                      'PASS' if ok else 'FAIL'])
        threads.remove(node)
        threads.remove(driver)
    return table, passed


def print_table(title: str, header: list[str], rows: list[list[str]], markdown: bool) -> None:
    print(f'\n{title}')
    if markdown:
        print('| ' + ' | '.join(header) + ' |')
        print('|' + '---|' * len(header))
        for row in rows:
            print('| ' + ' | '.join(row) + ' |')
        return
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print('  '.join(h.ljust(w) for h, w in zip(header, widths, strict=True)))
    for row in rows:
        print('  '.join(c.ljust(w) for c, w in zip(row, widths, strict=True)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', type=Path, default=Path(__file__).resolve().parents[2]
                        / 'shared' / 'data')
    parser.add_argument('--passes', type=int, default=3)
    parser.add_argument('--rate', type=float, default=100.0, help='stamp rate, Hz')
    parser.add_argument('--speed', type=float, default=1.0,
                        help='publish this many times faster than the stamps (same decisions)')
    parser.add_argument('--wrong-file-runs', type=int, default=3)
    parser.add_argument('--skip-recordings', action='store_true')
    parser.add_argument('--only', nargs='+', metavar='NAME',
                        help='replay only the recordings whose name contains one of these')
    parser.add_argument('--markdown', action='store_true')
    parser.add_argument('--fresh-noise', type=float, default=0.0, metavar='F',
                        help='add new Gaussian noise of F x |raw| per axis to every pass '
                        '(0.003: 0.3 %%); 0 replays the same readings each pass')
    parser.add_argument('--offline', action='store_true',
                        help='stream through CalibrationSession (inline runner) instead of the '
                        'node over DDS: the same decisions, no wrong-file section')
    args = parser.parse_args(argv)
    context = Context()
    rclpy.init(args=[], context=context)
    threads = NodeThreads(context)
    passed = True
    started = time.monotonic()
    try:
        with tempfile.TemporaryDirectory() as directory:
            os.environ['ROS_HOME'] = directory  # nothing written to the user's ~/.ros
            if not args.skip_recordings:
                rows, ok = recordings_section(threads, context, Path(directory), args)
                passed &= ok
                noise = (f'fresh noise {args.fresh_noise:g} x |raw| each pass'
                         if args.fresh_noise > 0.0 else 'exact replay')
                print_table(
                    f"(a) {'offline session' if args.offline else 'live node'}, defaults, "
                    f'{args.passes} passes at {args.rate:.0f} Hz, {noise}: magnitude spread '
                    'std/mean of |corrected|, % (* the all-rows fit fails its own gates; ratios '
                    'to the all-rows fit; robust: 1.4826 MAD/median; calibrate: after '
                    '~/calibrate at the end, † it failed its gates and the live one stayed)',
                    ['recording', 'rows', 'received', 'all-rows fit', 'live, last pass',
                     'ratio', 'robust ratio', 'calibrate ratio',
                     f'<= calibrate + {TARGET_OVER_CALIBRATE}', 'first corrected msg',
                     'converged at msg', 'adopted', 'final state'], rows, args.markdown)
            if not args.offline:
                rows, ok = wrong_file_section(threads, context, Path(directory), args)
                passed &= ok
                print_table('(b) wrong calibration file (another board), sim tumbling at '
                            '100 Hz: seconds from the first message',
                            ['run', 'node start s', 'WARN after s', 'recalibrated after s',
                             f'<= {WARN_TARGET_S:.0f} / {RECALIBRATED_TARGET_S:.0f} s'],
                            rows, args.markdown)
    finally:
        threads.shutdown()
        rclpy.try_shutdown(context=context)
    verdict = 'PASS' if passed else 'FAIL'
    print(f'\ntargets: {verdict} (run time {time.monotonic() - started:.0f} s, '
          f'ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
