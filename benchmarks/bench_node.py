#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Throughput and added latency of the mag_calibrator node against a bare rclpy relay.

Three processes per measurement, all over real DDS on localhost in a private ROS_DOMAIN_ID:
a feeder publishing sensor_msgs/MagneticField on ``imu/mag`` at a fixed rate, the system under
test (the ``mag_calibrator`` node with a calibration loaded, or a bare subscribe-copy-publish
relay: the ceiling any rclpy node can reach), and this process as the sink on
``imu/mag_corrected``. The feeder stamps each message with its send time; the sink records
receive time minus stamp, so the node's *added* latency is its latency minus the relay's.

    python benchmarks/bench_node.py                 # rates 100, 500, 1000, 2000 Hz, 10 s each
    python benchmarks/bench_node.py --rates 1000 --duration 5 --markdown
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
import threading
import time

import numpy as np

SUT_READY_TIMEOUT_S = 30.0
SETTLE_S = 1.0
MATCH_TIMEOUT_S = 30.0
DRAIN_S = 1.5


def _feeder(rate_hz: float, duration_s: float, start_delay_s: float) -> int:
    """Publish a distorted tumbling field at ``rate_hz`` for ``duration_s`` (reliable QoS)."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import MagneticField

    from mag_calibrator_ros.sim.motion import body_field_samples

    count = int(rate_hz * duration_s)
    rng = np.random.default_rng(1)
    truth = body_field_samples('tumble', count, rate_hz, 50e-6, 60.0, seed=1)
    raw = truth @ np.diag([1.1, 0.95, 1.0]).T + np.array([30e-6, -20e-6, 10e-6])
    raw += rng.normal(0.0, 0.3e-6, raw.shape)

    rclpy.init()
    node = rclpy.create_node('bench_feeder')
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    publisher = node.create_publisher(MagneticField, 'imu/mag', qos)
    # Discovery under load can take seconds: start only once the system under test has matched.
    deadline = time.monotonic() + MATCH_TIMEOUT_S
    while publisher.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            print('feeder: no subscriber matched imu/mag', file=sys.stderr)
            return 1
        time.sleep(0.05)
    time.sleep(start_delay_s)
    message = MagneticField()
    message.header.frame_id = 'imu_link'
    period = 1.0 / rate_hz
    next_send = time.perf_counter()
    for i in range(count):
        now = time.perf_counter()
        if now < next_send:
            time.sleep(next_send - now)
        next_send += period
        stamp_ns = time.time_ns()
        message.header.stamp.sec = stamp_ns // 1_000_000_000
        message.header.stamp.nanosec = stamp_ns % 1_000_000_000
        message.magnetic_field.x, message.magnetic_field.y, message.magnetic_field.z = (
            float(v) for v in raw[i]
        )
        publisher.publish(message)
    time.sleep(DRAIN_S)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _relay() -> int:
    """The ceiling: subscribe with the node's own input QoS, copy, publish."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import MagneticField

    from mag_calibrator_ros.nodes.mag_calibrator import INPUT_QOS

    rclpy.init()
    node = rclpy.create_node('bench_relay')
    out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    publisher = node.create_publisher(MagneticField, 'imu/mag_corrected', out_qos)

    def relay(message: MagneticField) -> None:
        copy = MagneticField()
        copy.header = message.header
        copy.magnetic_field = message.magnetic_field
        copy.magnetic_field_covariance = message.magnetic_field_covariance
        publisher.publish(copy)

    node.create_subscription(MagneticField, 'imu/mag', relay, INPUT_QOS)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


class _Sink:
    """Collects receive-minus-stamp latencies of ``imu/mag_corrected``."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import MagneticField

        self._rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node('bench_sink')
        self.latencies_ns: list[int] = []
        self._lock = threading.Lock()
        # Best effort matches any publisher; a deep queue keeps the sink from being the bottleneck.
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.node.create_subscription(MagneticField, 'imu/mag_corrected', self._on_message, qos)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _on_message(self, message) -> None:
        stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        with self._lock:
            self.latencies_ns.append(time.time_ns() - stamp)

    def take(self) -> list[int]:
        with self._lock:
            taken, self.latencies_ns = self.latencies_ns, []
        return taken

    def publishers_ready(self) -> bool:
        return self.node.count_publishers('imu/mag_corrected') > 0

    def close(self) -> None:
        self._executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def _write_calibration(directory: Path) -> Path:
    """A calibration file, so the node publishes corrected output from the first message."""
    from mag_calibrator_ros.calibration import Calibration
    from mag_calibrator_ros.calibration.store.calibration_file import save_calibration

    path = directory / 'calibration.yaml'
    calibration = Calibration(
        np.array([30e-6, -20e-6, 10e-6]), np.diag([1 / 1.1, 1 / 0.95, 1.0]), 50e-6, 'full'
    )
    save_calibration(path, calibration)
    return path


def _start_sut(kind: str, calibration_file: Path, buffer_size: int) -> subprocess.Popen:
    if kind == 'relay':
        command = [sys.executable, __file__, '--role', 'relay']
    else:
        command = [
            str(Path(sys.executable).parent / 'mag_calibrator'), '--ros-args',
            '-p', f'calibration_file:={calibration_file}',
            '-p', f'buffer_size:={buffer_size}',
            '-p', 'auto_calibrate:=false',
            '--log-level', 'warn',
        ]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _stop(process: subprocess.Popen) -> str:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.stderr.read() if process.stderr else ''


def _measure(sink: _Sink, kind: str, rate: float, duration: float, calibration_file: Path,
             buffer_size: int) -> dict[str, float]:
    sut = _start_sut(kind, calibration_file, buffer_size)
    try:
        deadline = time.monotonic() + SUT_READY_TIMEOUT_S
        while not sink.publishers_ready():
            if sut.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f'{kind} did not come up: {_stop(sut)[-2000:]}')
            time.sleep(0.1)
        sink.take()
        feeder = subprocess.run(
            [sys.executable, __file__, '--role', 'feed', '--rate', str(rate),
             '--duration', str(duration), '--start-delay', str(SETTLE_S)],
            capture_output=True, text=True, timeout=duration + 60,
        )
        if feeder.returncode != 0:
            raise RuntimeError(f'feeder failed: {feeder.stderr[-2000:]}')
        time.sleep(0.2)
        latencies = np.array(sink.take(), dtype=float) / 1e6
    finally:
        _stop(sut)
    sent = int(rate * duration)
    received = latencies.size
    return {
        'sent': sent,
        'received': received,
        'loss_pct': 100.0 * max(sent - received, 0) / sent,
        'throughput_hz': received / duration,
        'p50_ms': float(np.percentile(latencies, 50)) if received else float('nan'),
        'p99_ms': float(np.percentile(latencies, 99)) if received else float('nan'),
    }


def _report(results: dict[tuple[str, float], dict[str, float]], rates: list[float],
            markdown: bool) -> bool:
    header = ('rate Hz', 'relay out/s', 'node out/s', 'node/relay', 'node loss %',
              'relay p50/p99 ms', 'node p50/p99 ms', 'added p50/p99 ms')
    rows = []
    passed = True
    for rate in rates:
        relay, node = results[('relay', rate)], results[('node', rate)]
        ratio = node['throughput_hz'] / relay['throughput_hz'] if relay['throughput_hz'] else 0.0
        rows.append((
            f'{rate:.0f}', f'{relay["throughput_hz"]:.0f}', f'{node["throughput_hz"]:.0f}',
            f'{100 * ratio:.0f} %', f'{node["loss_pct"]:.2f}',
            f'{relay["p50_ms"]:.2f} / {relay["p99_ms"]:.2f}',
            f'{node["p50_ms"]:.2f} / {node["p99_ms"]:.2f}',
            f'{node["p50_ms"] - relay["p50_ms"]:.2f} / {node["p99_ms"] - relay["p99_ms"]:.2f}',
        ))
        passed &= ratio >= 0.8
        if rate == 1000:
            passed &= node['loss_pct'] == 0.0
    if markdown:
        print('| ' + ' | '.join(header) + ' |')
        print('|' + '---|' * len(header))
        for row in rows:
            print('| ' + ' | '.join(row) + ' |')
    else:
        widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
        print('  '.join(h.rjust(w) for h, w in zip(header, widths, strict=True)))
        for row in rows:
            print('  '.join(c.rjust(w) for c, w in zip(row, widths, strict=True)))
    return passed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--role', choices=['bench', 'feed', 'relay'], default='bench')
    parser.add_argument('--rates', type=float, nargs='+', default=[100, 500, 1000, 2000])
    parser.add_argument('--rate', type=float, default=1000.0)
    parser.add_argument('--duration', type=float, default=10.0)
    parser.add_argument('--start-delay', type=float, default=SETTLE_S)
    parser.add_argument('--buffer-size', type=int, default=100)
    parser.add_argument('--markdown', action='store_true')
    args = parser.parse_args(argv)

    if args.role == 'feed':
        return _feeder(args.rate, args.duration, args.start_delay)
    if args.role == 'relay':
        return _relay()

    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(150, 200)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    sink = _Sink()
    results = {}
    with tempfile.TemporaryDirectory() as directory:
        calibration_file = _write_calibration(Path(directory))
        try:
            for rate in args.rates:
                for kind in ('relay', 'node'):
                    results[(kind, rate)] = _measure(
                        sink, kind, rate, args.duration, calibration_file, args.buffer_size
                    )
                    print(f'  {kind:5s} at {rate:6.0f} Hz: {results[(kind, rate)]}',
                          file=sys.stderr)
        finally:
            sink.close()
    print(f'mag_calibrator vs bare rclpy relay, buffer N={args.buffer_size}, '
          f'{args.duration:.0f} s per rate, ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}')
    passed = _report(results, args.rates, args.markdown)
    print('targets (>= 80 % of relay throughput, no loss at 1 kHz):',
          'PASS' if passed else 'FAIL')
    return 0


if __name__ == '__main__':
    sys.exit(main())
