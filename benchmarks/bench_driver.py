#!/usr/bin/env python3
"""icm20948_driver (simulated chip) over real DDS: publish rate and jitter, CPU share, faults.

The driver node runs in its own process (so its CPU share is its own: process time / wall time,
all threads, DDS included); this process subscribes to ``imu/mag`` and measures what arrives.
Scenarios, all at rate_hz 100 in a private ROS_DOMAIN_ID on localhost:

- nominal: 30 s; published rate from header stamps, interval jitter (std, p99, max), CPU share.
- 5 % I2C errors: sim.i2c_error_rate 0.05; published rate, errors, re-initialisations.
- 2 s outage: the device vanishes 5 s in (and comes back power-cycled); published rate outside
  the outage, and recovery time = first stamp after the outage ends - outage end.

    python benchmarks/bench_driver.py                 # 30 s nominal, 20 s per fault scenario
    python benchmarks/bench_driver.py --duration 10   # quicker
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import subprocess
import sys
import threading
import time

import numpy as np

WARMUP_S = 2.0
RATE_HZ = 100
OUTAGE_AT_S = 5.0
OUTAGE_S = 2.0


def _driver_process(duration_s: float, error_rate: float, outage: bool) -> int:
    """Child: run the node for warm-up + duration; print its own counters and CPU as JSON."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode

    rclpy.init()
    node = Icm20948DriverNode(parameter_overrides=[
        Parameter('backend', value='sim'),
        Parameter('rate_hz', value=RATE_HZ),
        Parameter('sim.i2c_error_rate', value=error_rate),
        Parameter('sim.seed', value=1),
    ])
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    go = threading.Event()  # the parent says GO once its subscriber receives our messages
    threading.Thread(target=lambda: (sys.stdin.readline(), go.set()), daemon=True).start()
    print('READY', flush=True)
    measure_from = time.monotonic() + WARMUP_S
    stop_at = math.inf
    outage_start_ros = None
    cpu0 = wall0 = None
    while True:
        now = time.monotonic()
        if now >= stop_at:
            break
        if cpu0 is None and now >= measure_from and go.is_set():
            cpu0, wall0 = time.process_time(), now
            published0 = node.published
            measure_from, stop_at = now, now + duration_s
        if outage and outage_start_ros is None and now >= measure_from + OUTAGE_AT_S:
            outage_start_ros = time.time()
            node.simulator.start_outage(OUTAGE_S)
        executor.spin_once(timeout_sec=0.05)
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    result = {
        'cpu_share': cpu / wall,
        'published': node.published - published0,
        'measure_from': time.time() - wall,  # wall-clock (ROS system time) window
        'measure_to': time.time(),
        'i2c_errors': node.i2c_errors,
        'reinitialisations': node.reinitialisations,
        'overruns': node.overruns,
        'outage_start': outage_start_ros,
        'node_recovery_s': node.last_recovery_s,
    }
    time.sleep(0.5)  # let the last messages drain before leaving the graph
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    print('RESULT ' + json.dumps(result), flush=True)
    return 0


class _Sink:
    """Receives imu/mag (reliable, deep queue) in a background executor; keeps header stamps."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import MagneticField

        rclpy.init()
        self._rclpy = rclpy
        self.node = rclpy.create_node('bench_driver_sink')
        self._stamps: list[float] = []
        self._lock = threading.Lock()
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(MagneticField, 'imu/mag', self._on_message, qos)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self._executor.spin()
        except ExternalShutdownException:
            pass  # close() shut rclpy down

    def _on_message(self, message) -> None:
        with self._lock:
            self._stamps.append(message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec)

    def take(self) -> np.ndarray:
        with self._lock:
            taken, self._stamps = self._stamps, []
        return np.array(taken)

    def close(self) -> None:
        self._rclpy.try_shutdown()  # wakes the spinning thread, which then returns
        self._thread.join(timeout=5.0)
        self.node.destroy_node()


def run_scenario(sink: _Sink, name: str, duration_s: float, error_rate: float = 0.0,
                 outage: bool = False) -> dict:
    command = [sys.executable, __file__, '--driver-process', '--duration', str(duration_s),
               '--error-rate', str(error_rate)] + (['--outage'] if outage else [])
    child = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == 'READY', 'driver process failed to start'
    deadline = time.monotonic() + 30.0
    while len(sink.take()) == 0 and time.monotonic() < deadline:  # DDS discovery done
        time.sleep(0.1)
    output, _ = child.communicate('GO\n', timeout=duration_s + 90)
    if child.returncode != 0:
        raise RuntimeError(f'{name}: driver process exited {child.returncode}')
    result = json.loads(next(line for line in output.splitlines()
                             if line.startswith('RESULT '))[len('RESULT '):])
    time.sleep(0.2)
    stamps = np.sort(sink.take())
    stamps = stamps[(stamps >= result['measure_from']) & (stamps <= result['measure_to'])]
    window = result['measure_to'] - result['measure_from']
    intervals = np.diff(stamps) * 1e3
    row = {
        'scenario': name,
        'received': len(stamps),
        'published': result['published'],
        'rate_hz': len(stamps) / window,
        'node_rate_hz': result['published'] / window,
        'interval_ms': float(np.mean(intervals)) if len(intervals) else float('nan'),
        'jitter_ms': float(np.std(intervals)) if len(intervals) else float('nan'),
        'p99_ms': float(np.percentile(intervals, 99)) if len(intervals) else float('nan'),
        'max_gap_ms': float(np.max(intervals)) if len(intervals) else float('nan'),
        'cpu_pct': 100.0 * result['cpu_share'],
        'i2c_errors': result['i2c_errors'],
        'reinits': result['reinitialisations'],
        'overruns': result['overruns'],
        'recovery_s': float('nan'),
    }
    if outage and result['outage_start'] is not None:
        start = result['outage_start']
        end = start + OUTAGE_S
        after = stamps[stamps >= end]
        row['recovery_s'] = float(after[0] - end) if len(after) else float('inf')
        outside = (stamps < start) | (stamps >= end)
        row['rate_hz'] = int(np.count_nonzero(outside)) / (window - OUTAGE_S)
        row['in_outage'] = int(np.count_nonzero(~outside))
    return row


def print_table(rows: list[dict]) -> None:
    columns = [('scenario', '{}'), ('rate_hz', '{:.2f}'), ('node_rate_hz', '{:.2f}'),
               ('interval_ms', '{:.2f}'),
               ('jitter_ms', '{:.2f}'), ('p99_ms', '{:.1f}'), ('max_gap_ms', '{:.0f}'),
               ('cpu_pct', '{:.1f}'), ('i2c_errors', '{}'), ('reinits', '{}'),
               ('overruns', '{}'), ('recovery_s', '{:.2f}')]
    cells = [[fmt.format(row[key]) for key, fmt in columns] for row in rows]
    widths = [max(len(key), *(len(c[i]) for c in cells)) for i, (key, _) in enumerate(columns)]
    print(' | '.join(key.ljust(w) for (key, _), w in zip(columns, widths, strict=True)))
    print('-|-'.join('-' * w for w in widths))
    for c in cells:
        print(' | '.join(v.ljust(w) for v, w in zip(c, widths, strict=True)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--duration', type=float, default=30.0, help='nominal scenario (s)')
    parser.add_argument('--fault-duration', type=float, default=20.0, help='fault scenarios (s)')
    parser.add_argument('--driver-process', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--error-rate', type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument('--outage', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.driver_process:
        return _driver_process(args.duration, args.error_rate, args.outage)

    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(101, 180)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    sink = _Sink()
    try:
        rows = [
            run_scenario(sink, f'nominal {RATE_HZ} Hz', args.duration),
            run_scenario(sink, '5% I2C errors', args.fault_duration, error_rate=0.05),
            run_scenario(sink, f'{OUTAGE_S:g} s outage', args.fault_duration, outage=True),
        ]
    finally:
        sink.close()
    print(f'\nicm20948_driver, sim backend, requested {RATE_HZ} Hz, ROS_DOMAIN_ID '
          f"{os.environ['ROS_DOMAIN_ID']}. rate_hz: received, from header stamps (outage row: "
          f'outside the outage); node_rate_hz: published by the node over the whole window; '
          f'recovery = first stamp after the device is back.\n')
    print_table(rows)
    outage_row = rows[2]
    print(f"\nmessages stamped inside the outage: {outage_row.get('in_outage')}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
