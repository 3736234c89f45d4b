#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Ground robots: a simulated robot that turns only on cmd_vel, calibrated by turning in place.

The robot (sim.motion cmd_vel): field 50 uT at 60° inclination, hard iron (55, -45, 25) uT
(75 uT, three times the 25 uT horizontal field), strong soft iron (scales 0.85-1.15,
off-diagonals up to 0.12), 2° of tilt wobble that follows the heading (an uneven floor), noise
0.3 uT, 100 Hz. Over real DDS, every node in this process on its own thread (NodeThreads), the
signal runs with ``mag_calibrator`` in a process of its own.

(a) ~/rotate_and_calibrate at the default 0.3 rad/s: seconds of turning until the calibrator
    stops the robot calibrated, and degrees turned (target: calibrated within 40 s).
(b) Heading error of that calibration (target <= 0.5° RMS over a full turn, goal 0.3°): the
    azimuth about the chip z axis of the corrected field against the true one, (i) the
    calibration alone on noise-free readings over a full turn of the same floor, (ii) the live
    corrected stream while the benchmark turns the robot once more at 0.6 rad/s (noise
    included: 0.3 uT on a 25 uT horizontal field is about 0.7° per sample). The same for a
    robot without wobble and with 1° (the calibration alone).
(c) Without the service: a teleop turns the robot at 0.3 rad/s; seconds until the calibrator
    (default parameters) has calibrated by itself.
(d) Every stop path, several times each: seconds from its cause to the zero twist arriving at a
    subscriber (target: within 0.2 s), and that nothing but zeros follows it. Causes: the fit's
    answer (done), ~/stop_rotation sent, the timeout reached, the magnetometer's last message +
    0.5 s (no input), the fit failing (an injected error), another publisher created on cmd_vel,
    the parameter change sent, the node destroyed, SIGTERM and SIGINT sent to the process (the
    last twist after it exited must be zero).

    python benchmarks/bench_ground.py                 # about 6 minutes
    python benchmarks/bench_ground.py --seeds 1 --repeats 2   # quicker
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(151, 199)))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from geometry_msgs.msg import Twist  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from mag_calibrator_ros.calibration.live.jobs import JobOutcome
from mag_calibrator_ros.calibration.live.turning import INPUT_HOLD_S  # noqa: E402
from mag_calibrator_ros.calibration.live.worker import InlineRunner  # noqa: E402
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode  # noqa: E402
from mag_calibrator_ros.nodes.runtime import NodeThreads, wait_until  # noqa: E402
from mag_calibrator_ros.sim import motion  # noqa: E402
from mag_calibrator_ros.tools.demo import (  # noqa: E402
    GROUND_HARD_IRON_UT,
    GroundObserver,
    azimuth_errors_deg,
    simulated_board,
    turn_full_circle,
)

WOBBLE_DEG = 2.0
CHECK_RATE = 0.6
CALIBRATED_TARGET_S = 40.0
HEADING_TARGET_DEG = 0.5
HEADING_GOAL_DEG = 0.3
STOP_TARGET_S = 0.2
TIMEOUT_S = 5.0  # rotation_timeout of the timeout path (its minimum)


class Station(GroundObserver):
    """The benchmark as a user: the demo's ground-robot observer (raw and corrected streams
    paired by stamp, the rotation services, a teleop) that also records every twist on cmd_vel."""

    def __init__(self, context: Context, namespace: str) -> None:
        super().__init__(context, namespace)
        self.twists: list[tuple[float, float]] = []
        self.create_subscription(Twist, 'cmd_vel', self._on_twist, 50)

    def _on_twist(self, message: Twist) -> None:
        with self._lock:
            self.twists.append((time.monotonic(), message.angular.z))

    def zero_after(self, moment: float) -> tuple[float | None, bool]:
        """(arrival of the first zero after ``moment``, whether only zeros followed it)."""
        with self._lock:
            after = [(t, z) for t, z in self.twists if t >= moment]
        for index, (t, z) in enumerate(after):
            if z == 0.0:
                return t, all(w == 0.0 for _, w in after[index:])
        return None, False

    def last_twist(self) -> float | None:
        with self._lock:
            return self.twists[-1][1] if self.twists else None

    def set_parameter(self, node: str, name: str, value) -> None:
        client = self.create_client(SetParameters, f'{node}/set_parameters')
        client.wait_for_service(timeout_sec=20.0)
        future = client.call_async(SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()]))
        wait(future.done, 20.0)
        self.destroy_client(client)


def wait(condition, timeout_s: float, step_s: float = 0.01) -> bool:
    """10 ms steps: the stop latencies below are read to that."""
    return wait_until(condition, timeout_s, step_s)


class Bench:
    def __init__(self, context: Context, workdir: Path) -> None:
        self.context = context
        self.workdir = workdir
        self.spinning = NodeThreads(context)
        self.count = 0

    def robot(self, namespace: str, seed: int, wobble_deg: float = WOBBLE_DEG):
        return self.spinning.add(simulated_board(
            self.context, 'cmd_vel', GROUND_HARD_IRON_UT, seed, namespace,
            tilt_wobble_deg=float(wobble_deg)))

    def calibrator(self, namespace: str, runner=None, **parameters) -> MagCalibratorNode:
        """``runner``: where its fits run (the node's own process by default)."""
        self.count += 1
        overrides = [Parameter('calibration_file',
                               value=str(self.workdir / f'{self.count}.yaml')),
                     Parameter('progress_log_period', value=0.0)]
        overrides += [Parameter(name, value=value) for name, value in parameters.items()]
        return self.spinning.add(MagCalibratorNode(
            namespace=namespace, context=self.context, parameter_overrides=overrides,
            runner=runner))

    def station(self, namespace: str) -> Station:
        return self.spinning.add(Station(self.context, namespace))

    def remove(self, *nodes) -> None:
        for node in nodes:
            if node is not None:
                self.spinning.remove(node)


def yaw(driver) -> tuple[float, float]:
    return driver.settings.cmd_vel.yaw_and_rate(driver.simulator.sim_time_s)


def start_rotation(station: Station) -> Trigger.Response | None:
    response = None
    for _ in range(40):  # until the first readings have arrived
        response = station.call(station.rotate)
        if response is None or response.success or 'no input' not in response.message:
            return response
        time.sleep(0.25)
    return response


def heading_rms(calibration, driver, seed: int, wobble_deg: float) -> float:
    """The calibration alone: noise-free readings over a full turn of the same floor."""
    config = driver.simulator.config
    trajectory = motion.CmdVelTrajectory(seed=seed, wobble_deg=wobble_deg)
    earth = motion.earth_field(config.field_ut, config.inclination_deg) * 1e-6
    truth = []
    for t in np.arange(0.0, 30.0, 0.02):
        trajectory.command(CHECK_RATE, float(t))
        truth.append(trajectory.state(float(t)).rotation.T @ earth)
    truth = np.array(truth[int(2.0 / 0.02):])  # once up to speed
    raw = truth @ config.soft_iron_matrix.T + config.hard_iron * 1e-6
    return float(np.sqrt(np.mean(azimuth_errors_deg(calibration.apply(raw), truth) ** 2)))


def live_heading_rms(station: Station, driver) -> tuple[float, int]:
    """Turn once more (the benchmark as a teleop) and score the corrected stream."""
    _, corrected, truth = turn_full_circle(station, driver, CHECK_RATE, 60.0)
    if not truth:
        return math.nan, 0
    errors = azimuth_errors_deg(np.array(corrected), np.array(truth))
    return float(np.sqrt(np.mean(errors**2))), len(errors)


def one_turn(bench: Bench, seed: int) -> dict:
    namespace = f'turn{seed}'
    driver = bench.robot(namespace, seed)
    calibrator = bench.calibrator(namespace)
    station = bench.station(namespace)
    try:
        response = start_rotation(station)
        if response is None or not response.success:
            return {'seed': seed, 'reason': f'not started: {response and response.message}'}
        started, start_yaw = time.monotonic(), yaw(driver)[0]
        rotation = calibrator._rotation
        wait(lambda: rotation.state != 'turning', 130.0, 0.05)
        row = {'seed': seed, 'reason': (rotation.last_stop or ('?', ''))[0],
               'seconds': rotation._stopped - started,
               'turned': math.degrees(abs(yaw(driver)[0] - start_yaw))}
        calibration = calibrator.session.calibration
        if calibration is not None:
            row['alone'] = heading_rms(calibration, driver, seed, WOBBLE_DEG)
            wait(lambda: rotation.state == 'idle', 5.0)
            row['live'], row['samples'] = live_heading_rms(station, driver)
        return row
    finally:
        bench.remove(station, calibrator, driver)


def calibrate_by_turning(bench: Bench, seeds: list[int]) -> list[dict]:
    rows = []
    for seed in seeds:
        row = one_turn(bench, seed)
        rows.append(row)
        print(f"  seed {seed}: {row['reason']} after {row.get('seconds', math.nan):.1f} s, "
              f"turned {row.get('turned', math.nan):.0f} deg; heading error alone "
              f"{row.get('alone', math.nan):.2f} deg, live {row.get('live', math.nan):.2f} deg "
              f"RMS ({row.get('samples', 0)} samples)")
    return rows


def one_wobble(bench: Bench, wobble: float, seed: int) -> float:
    namespace = f'wobble{int(wobble)}_{seed}'
    driver = bench.robot(namespace, seed, wobble)
    calibrator = bench.calibrator(namespace)
    station = bench.station(namespace)
    try:
        response = start_rotation(station)
        if response is None or not response.success:
            return math.nan
        rotation = calibrator._rotation
        wait(lambda: rotation.state != 'turning', 130.0, 0.05)
        calibration = calibrator.session.calibration
        return math.nan if calibration is None else heading_rms(calibration, driver, seed,
                                                                wobble)
    finally:
        bench.remove(station, calibrator, driver)


def wobble_sweep(bench: Bench, seeds: list[int]) -> dict[float, list[float]]:
    """The calibration alone for robots with less wobble (by turning, as above)."""
    sweep: dict[float, list[float]] = {}
    for wobble in (0.0, 1.0):
        sweep[wobble] = [one_wobble(bench, wobble, seed) for seed in seeds]
        print(f'  wobble {wobble:.0f} deg: heading error alone '
              + ', '.join(f'{e:.2f}' for e in sweep[wobble]) + ' deg RMS')
    return sweep


def one_teleop(bench: Bench, seed: int) -> float:
    namespace = f'teleop{seed}'
    driver = bench.robot(namespace, seed)
    calibrator = bench.calibrator(namespace)
    station = bench.station(namespace)
    session = calibrator.session
    try:
        wait(lambda: session.report().counts.accepted > 20, 20.0)
        started = time.monotonic()

        def turned() -> bool:
            station.turn(0.3)
            return session.calibration is not None

        calibrated = wait(turned, 120.0, 0.05)
        station.release()
        return time.monotonic() - started if calibrated else math.nan
    finally:
        bench.remove(station, calibrator, driver)


def calibrate_by_teleop(bench: Bench, seeds: list[int]) -> list[float]:
    times = []
    for seed in seeds:
        times.append(one_teleop(bench, seed))
        print(f'  seed {seed}: calibrated by itself after {times[-1]:.1f} s of teleop turning')
    return [t for t in times if math.isfinite(t)]


class FailingRequests(InlineRunner):
    """Every requested fit fails with an error, as if the worker died."""

    def submit(self, job) -> None:
        if job.ticket is None:
            super().submit(job)
        else:
            self._outcome = JobOutcome(job, error='injected: fit worker process ended')


STOP_PATHS = ('done', 'stop_rotation', 'timeout', 'no_input', 'fit_error', 'conflict',
              'parameter', 'destroy')


def one_stop(bench: Bench, path: str, attempt: int) -> tuple[float, bool] | None:
    """(seconds from the cause to the zero at the subscriber, only zeros after it)."""
    namespace = f'stop_{path}_{attempt}'
    driver = bench.robot(namespace, attempt)
    parameters = {'rotation_timeout': TIMEOUT_S} if path == 'timeout' else {}
    runner = FailingRequests() if path == 'fit_error' else None
    calibrator = bench.calibrator(namespace, runner, **parameters)
    rotation = calibrator._rotation
    station = bench.station(namespace)
    try:
        response = start_rotation(station)
        if response is None or not response.success:
            print(f'  {path}: not started: {response and response.message}')
            return None
        started = time.monotonic()
        wait(lambda: yaw(driver)[1] > 0.2, 10.0)
        if path in ('done', 'fit_error'):
            wait(lambda: rotation.state != 'turning', 130.0, 0.005)
            cause = rotation._stopped  # the fit's answer came: the stop decision
        elif path == 'stop_rotation':
            cause = time.monotonic()
            station.call(station.stop_rotation)
        elif path == 'timeout':
            cause = started + TIMEOUT_S  # from the service's answer: slightly late, if anything
            wait(lambda: rotation.state != 'turning', 30.0, 0.005)
        elif path == 'no_input':
            bench.remove(driver)
            cause = time.monotonic() + INPUT_HOLD_S  # the last reading came before this
            driver = None
        elif path == 'conflict':
            cause = time.monotonic()
            station.turn(0.0)  # a teleop appears (both then publish zeros)
        elif path == 'parameter':
            cause = time.monotonic()
            station.set_parameter(calibrator.get_fully_qualified_name(), 'rotation_speed', 0.4)
        else:  # destroy
            cause = time.monotonic()
            bench.remove(calibrator)
            calibrator = None
        if not wait(lambda: station.zero_after(cause - 0.001)[0] is not None, 10.0):
            return math.nan, False
        time.sleep(0.6)
        arrived, clean = station.zero_after(cause - 0.001)
        return arrived - cause, clean or path == 'conflict'
    finally:
        station.release()
        bench.remove(station, calibrator, driver)


def stop_paths(bench: Bench, repeats: int) -> dict[str, list[tuple[float, bool]]]:
    """(latency s, only zeros after) of every stop path, ``repeats`` times each."""
    results: dict[str, list[tuple[float, bool]]] = {}
    for path in STOP_PATHS:
        values = [v for v in (one_stop(bench, path, a) for a in range(repeats)) if v]
        results[path] = values
        print(f'  {path:13s} ' + ', '.join(f'{1e3 * v:.0f}' for v, _ in values) + ' ms'
              + ('' if all(c for _, c in values) else '  NON-ZERO AFTER THE STOP'))
    return results


def one_signal(bench: Bench, stop_signal: signal.Signals, attempt: int
               ) -> tuple[float, bool] | None:
    namespace = f'signal_{stop_signal.name.lower()}_{attempt}'
    driver = bench.robot(namespace, attempt)
    station = bench.station(namespace)
    process = subprocess.Popen(
        [sys.executable, '-m', 'mag_calibrator_ros.nodes.mag_calibrator', '--ros-args',
         '-r', f'__ns:=/{namespace}',
         '-p', f'calibration_file:={bench.workdir / (namespace + ".yaml")}'],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        response = start_rotation(station)
        if response is None or not response.success:
            return None
        if not wait(lambda: (station.last_twist() or 0.0) > 0.2, 20.0):
            return None
        cause = time.monotonic()
        process.send_signal(stop_signal)
        process.wait(timeout=30.0)
        time.sleep(1.0)  # anything still on its way arrives
        arrived, clean = station.zero_after(cause)
        clean = clean and station.last_twist() == 0.0
        return (math.nan if arrived is None else arrived - cause), clean
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        bench.remove(station, driver)


def signal_paths(bench: Bench, repeats: int) -> dict[str, list[tuple[float, bool]]]:
    results: dict[str, list[tuple[float, bool]]] = {}
    for stop_signal in (signal.SIGTERM, signal.SIGINT):
        values = [v for v in (one_signal(bench, stop_signal, a) for a in range(repeats)) if v]
        results[stop_signal.name] = values
        print(f'  {stop_signal.name:13s} ' + ', '.join(f'{1e3 * v:.0f}' for v, _ in values)
              + ' ms' + ('' if all(c for _, c in values) else '  NON-ZERO AFTER EXIT'))
    return results


def summary(turns, sweep, teleop, stops) -> None:
    print('\n## Summary\n')
    done = [r for r in turns if r['reason'] == 'done']
    if done:
        seconds = [r['seconds'] for r in done]
        verdict = 'PASS' if max(seconds) <= CALIBRATED_TARGET_S else 'FAIL'
        print(f'calibrated by ~/rotate_and_calibrate: {len(done)}/{len(turns)} runs, '
              f'{min(seconds):.1f}-{max(seconds):.1f} s of turning (target '
              f'{CALIBRATED_TARGET_S:.0f} s: {verdict}), turned '
              f'{min(r["turned"] for r in done):.0f}-{max(r["turned"] for r in done):.0f} deg')
        alone = [r['alone'] for r in done]
        live = [r['live'] for r in done if math.isfinite(r.get('live', math.nan))]
        verdict = ('PASS (goal too)' if max(alone) <= HEADING_GOAL_DEG else 'PASS'
                   if max(alone) <= HEADING_TARGET_DEG else 'FAIL')
        print(f'heading error, {WOBBLE_DEG:.0f} deg wobble: calibration alone '
              f'{min(alone):.2f}-{max(alone):.2f} deg RMS (target {HEADING_TARGET_DEG} deg: '
              f'{verdict}); live with noise {min(live, default=math.nan):.2f}-'
              f'{max(live, default=math.nan):.2f} deg RMS')
    for wobble, errors in sorted(sweep.items()):
        print(f'heading error, {wobble:.0f} deg wobble: calibration alone {min(errors):.2f}-'
              f'{max(errors):.2f} deg RMS')
    if teleop:
        print(f'calibrated by itself while a teleop turned it: {min(teleop):.1f}-'
              f'{max(teleop):.1f} s')
    print('\n| stop path | runs | median ms | max ms | only zeros after |')
    print('|---|---:|---:|---:|---|')
    worst = 0.0
    for path, values in stops.items():
        latencies = [v for v, _ in values if math.isfinite(v)]
        worst = max([worst, *latencies])
        print(f'| {path} | {len(values)} | {1e3 * statistics.median(latencies):.0f} | '
              f'{1e3 * max(latencies):.0f} | {"yes" if all(c for _, c in values) else "NO"} |'
              if latencies else f'| {path} | {len(values)} | - | - | NO ZERO |')
    print(f'\nworst stop latency {1e3 * worst:.0f} ms (target {1e3 * STOP_TARGET_S:.0f} ms: '
          f'{"PASS" if worst <= STOP_TARGET_S else "FAIL"})')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seeds', type=int, default=3, help='robots (seeds) per measurement')
    parser.add_argument('--repeats', type=int, default=3, help='runs of each stop path')
    args = parser.parse_args(argv)
    seeds = list(range(1, args.seeds + 1))
    context = Context()
    rclpy.init(args=[], context=context)
    with tempfile.TemporaryDirectory(prefix='bench_ground_') as workdir:
        bench = Bench(context, Path(workdir))
        try:
            print('(a, b) ~/rotate_and_calibrate at 0.3 rad/s, 2 deg wobble')
            turns = calibrate_by_turning(bench, seeds)
            print('(b) less wobble')
            sweep = wobble_sweep(bench, seeds)
            print('(c) no service: a teleop turns the robot at 0.3 rad/s')
            teleop = calibrate_by_teleop(bench, seeds)
            print('(d) stop paths: cause -> zero twist at a subscriber')
            stops = stop_paths(bench, args.repeats)
            stops.update(signal_paths(bench, args.repeats))
            summary(turns, sweep, teleop, stops)
        finally:
            bench.spinning.shutdown()
            rclpy.try_shutdown(context=context)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
