#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Does a first view subscriber or a first GPS fix stall ``imu/mag_corrected`` at 1 kHz?

Four processes over real DDS in a private ROS_DOMAIN_ID: a feeder publishing
sensor_msgs/MagneticField on ``imu/mag`` at ``--rate`` (bench_node.py's), the ``mag_calibrator``
node under test with a calibration file (so it publishes from the first message), a bare rclpy
relay of the same input to ``relay/mag_corrected`` (a control: what the machine's scheduling
does to any rclpy node at that moment), and this process as the sink of both. After
``--settle`` seconds a subscriber of the node's three RViz view topics appears (RViz opening
the view: the first view is computed and published); ``--gap`` seconds later one
sensor_msgs/NavSatFix with STATUS_FIX arrives on ``gps/fix`` (the first location: the World
Magnetic Model's field is computed on the node's I/O thread).

For each window (before either, from the view subscription on, from the fix on, each
``--window`` seconds) it prints the largest gap between consecutive arrivals and the largest
stamp-to-arrival latency, for the node and for the relay. A stall of the node's message path
shows as a node gap well beyond the relay's in the same window. On a loaded computer both are
the scheduler's as much as the node's, so the node also runs instrumented: every callback on
its executor thread (message, poll, diagnostics and view, fix) and the World Magnetic Model's
field on its I/O thread are timed in wall time and in that thread's CPU time; the longest
callback's CPU time in a window is what the node's own work held the message path (a stall a
quiet computer would show), whatever the load.

    python benchmarks/bench_stalls.py                   # 1 kHz, 3 runs, a fresh node each
    python benchmarks/bench_stalls.py --runs 5 --markdown
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

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
READY_TIMEOUT_S = 60.0
BERLIN = (52.52, 13.40, 34.0)


def _instrumented_node(record: str) -> int:
    """The mag_calibrator node (its own ``main``) with every executor callback timed; the
    records (name, start s, wall ms, thread CPU ms) are written to ``record`` at exit."""
    import atexit
    import json

    from mag_calibrator_ros.nodes import mag_calibrator

    records: list[tuple[str, float, float, float]] = []

    def timed(name: str, method):
        def callback(self, *args):
            start, cpu = time.time(), time.thread_time()
            try:
                return method(self, *args)
            finally:
                records.append((name, start, (time.time() - start) * 1e3,
                                (time.thread_time() - cpu) * 1e3))
        return callback

    node_class = mag_calibrator.MagCalibratorNode
    for name in ('_on_mag', '_on_poll', '_on_tick', '_on_fix'):
        setattr(node_class, name, timed(name, getattr(node_class, name)))
    # the model's field, on the I/O thread: it holds the interpreter while it runs Python
    field = timed('earth_field on the I/O thread', lambda _, *where: earth_field(*where))
    earth_field = mag_calibrator.earth_field
    mag_calibrator.earth_field = lambda *where: field(None, *where)
    atexit.register(lambda: Path(record).write_text(json.dumps(records)))
    return mag_calibrator.main(sys.argv[sys.argv.index('--ros-args'):])


def _relay() -> int:
    """A bare subscribe-copy-publish relay, imu/mag -> relay/mag_corrected, the node's QoS."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import MagneticField

    from mag_calibrator_ros.nodes.mag_calibrator import INPUT_QOS

    rclpy.init(args=[])
    node = rclpy.create_node('bench_stall_relay')
    publisher = node.create_publisher(MagneticField, 'relay/mag_corrected', QoSProfile(depth=10))

    def relay(message: MagneticField) -> None:
        copy = MagneticField()
        copy.header = message.header
        copy.magnetic_field = message.magnetic_field
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
    """Arrival times and latencies of the node's and the relay's output, a view subscriber on
    demand, and the GPS fix publisher."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import MagneticField, NavSatFix

        self._rclpy = rclpy
        rclpy.init(args=[])
        self.node = rclpy.create_node('bench_stall_sink')
        self._lock = threading.Lock()
        self.arrivals: dict[str, list[tuple[float, float]]] = {'node': [], 'relay': []}
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
        for key, topic in (('node', 'imu/mag_corrected'), ('relay', 'relay/mag_corrected')):
            self.node.create_subscription(
                MagneticField, topic, lambda message, key=key: self._on(key, message), qos)
        self.fix_publisher = self.node.create_publisher(NavSatFix, 'gps/fix', 10)
        self.views_seen = 0
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _on(self, key: str, message) -> None:
        now = time.time_ns()
        stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        with self._lock:
            self.arrivals[key].append((now / 1e9, (now - stamp) / 1e6))

    def _on_view(self, _message) -> None:
        with self._lock:
            self.views_seen += 1

    def subscribe_view(self) -> None:
        """What RViz does when the view is opened: subscribe the three latched topics."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        prefix = '/mag_calibrator/view/'
        self.node.create_subscription(PointCloud2, prefix + 'raw', self._on_view, latched)
        self.node.create_subscription(PointCloud2, prefix + 'corrected', self._on_view, latched)
        self.node.create_subscription(MarkerArray, prefix + 'markers', self._on_view, latched)

    def publish_fix(self) -> None:
        from sensor_msgs.msg import NavSatFix, NavSatStatus

        fix = NavSatFix()
        fix.header.frame_id = 'gps'
        stamp = time.time_ns()
        fix.header.stamp.sec, fix.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        fix.status.status = NavSatStatus.STATUS_FIX
        fix.latitude, fix.longitude, fix.altitude = BERLIN
        self.fix_publisher.publish(fix)

    def ready(self) -> bool:
        return (self.node.count_publishers('imu/mag_corrected') > 0
                and self.node.count_publishers('relay/mag_corrected') > 0
                and self.fix_publisher.get_subscription_count() > 0)

    def take(self) -> dict[str, np.ndarray]:
        with self._lock:
            taken = {key: np.array(rows).reshape(-1, 2) for key, rows in self.arrivals.items()}
            for rows in self.arrivals.values():
                rows.clear()
        return taken

    def close(self) -> None:
        self._executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def _write_calibration(directory: Path) -> Path:
    from mag_calibrator_ros.calibration import Calibration
    from mag_calibrator_ros.calibration.store.calibration_file import save_calibration

    path = directory / 'calibration.yaml'
    save_calibration(path, Calibration(np.array([30e-6, -20e-6, 10e-6]),
                                       np.diag([1 / 1.1, 1 / 0.95, 1.0]), 50e-6, 'full'))
    return path


def _environment() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))


def _start(command: list[str]) -> subprocess.Popen:
    return subprocess.Popen(command, env=_environment(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _stop(process: subprocess.Popen) -> str:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGINT)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return process.stderr.read() if process.stderr else ''


def _window(rows: np.ndarray, start: float, end: float) -> tuple[float, float, int]:
    """(largest gap between arrivals ms, largest latency ms, messages) in [start, end)."""
    inside = rows[(rows[:, 0] >= start) & (rows[:, 0] < end)]
    if len(inside) < 2:
        return float('nan'), float('nan'), len(inside)
    times = np.concatenate([[start], inside[:, 0]])
    return float(np.max(np.diff(times)) * 1e3), float(np.max(inside[:, 1])), len(inside)


def _callbacks(records: list, start: float, end: float) -> tuple[float, float, str]:
    """(longest callback CPU ms, its wall ms, its name) of the node's callbacks in a window."""
    inside = [row for row in records if start <= row[1] < end]
    if not inside:
        return float('nan'), float('nan'), '-'
    name, _, wall, cpu = max(inside, key=lambda row: row[3])
    return cpu, wall, name.lstrip('_')


def run_once(sink: _Sink, calibration: Path, args: argparse.Namespace) -> dict[str, tuple]:
    record = calibration.parent / f'callbacks-{time.monotonic_ns()}.json'
    node = _start([sys.executable, __file__, '--role', 'node', '--record', str(record),
                   '--ros-args', '-p', f'calibration_file:={calibration}',
                   '-p', 'auto_calibrate:=false', '-p', 'use_imu:=false',
                   '--log-level', 'warn'])
    relay = _start([sys.executable, __file__, '--role', 'relay'])
    feeder = None
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not sink.ready():
            for process in (node, relay):
                if process.poll() is not None:
                    raise RuntimeError(f'a process ended: {_stop(process)[-2000:]}')
            if time.monotonic() > deadline:
                raise RuntimeError('the node or the relay did not come up')
            time.sleep(0.1)
        duration = args.settle + args.gap + args.window + 1.0
        feeder = _start([sys.executable, str(HERE / 'bench_node.py'), '--role', 'feed',
                         '--rate', str(args.rate), '--duration', str(duration),
                         '--start-delay', '0'])
        while not sink.take()['node'].size:  # the first corrected message
            if time.monotonic() > deadline or feeder.poll() is not None:
                raise RuntimeError(f'no corrected output: {_stop(feeder)[-2000:]}')
            time.sleep(0.05)
        began = time.time()
        time.sleep(args.settle)
        view_at = time.time()
        sink.subscribe_view()
        time.sleep(args.gap)
        fix_at = time.time()
        sink.publish_fix()
        time.sleep(args.window + 0.5)
        rows = sink.take()
    finally:
        for process in (feeder, relay, node):
            if process is not None:
                _stop(process)
    import json

    records = json.loads(record.read_text()) if record.exists() else []
    windows = {
        'before': (max(began, view_at - args.window), view_at),
        'view subscribed': (view_at, view_at + args.window),
        'first fix': (fix_at, fix_at + args.window),
    }
    return {name: (_window(rows['node'], *span), _window(rows['relay'], *span),
                   _callbacks(records, *span))
            for name, span in windows.items()} | {'views': sink.views_seen}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--role', choices=['bench', 'relay', 'node'], default='bench')
    parser.add_argument('--record', help=argparse.SUPPRESS)
    parser.add_argument('--rate', type=float, default=1000.0, help='input rate, Hz')
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--settle', type=float, default=4.0,
                        help='seconds of input before the view subscriber')
    parser.add_argument('--gap', type=float, default=4.0,
                        help='seconds between the view subscriber and the fix')
    parser.add_argument('--window', type=float, default=3.0, help='seconds per window')
    parser.add_argument('--markdown', action='store_true')
    argv = sys.argv[1:] if argv is None else argv
    ros_args = argv.index('--ros-args') if '--ros-args' in argv else len(argv)
    args = parser.parse_args(argv[:ros_args])
    if args.role == 'relay':
        return _relay()
    if args.role == 'node':
        return _instrumented_node(args.record)
    if args.gap < args.window:
        parser.error('--gap must be at least --window (the windows must not overlap)')
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(150, 230)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    results = []
    with tempfile.TemporaryDirectory() as directory:
        calibration = _write_calibration(Path(directory))
        for run in range(args.runs):
            sink = _Sink()  # a fresh sink: its view subscription is the node's first
            try:
                results.append(run_once(sink, calibration, args))
            finally:
                sink.close()
            load = ' '.join(f'{value:.1f}' for value in os.getloadavg())
            print(f'  run {run + 1} done (load {load}), views received '
                  f'{results[-1]["views"]}', file=sys.stderr)
    header = ('run', 'window', 'node max gap ms', 'relay max gap ms', 'node max latency ms',
              'relay max latency ms', 'node msgs', 'longest callback CPU / wall ms')
    rows = []
    for run, result in enumerate(results, 1):
        for name in ('before', 'view subscribed', 'first fix'):
            (gap, latency, count), (relay_gap, relay_latency, _), (cpu, wall, what) = (
                result[name])
            rows.append((str(run), name, f'{gap:.0f}', f'{relay_gap:.0f}', f'{latency:.0f}',
                         f'{relay_latency:.0f}', str(count), f'{cpu:.1f} / {wall:.0f} ({what})'))
    print(f'imu/mag_corrected at {args.rate:.0f} Hz, windows of {args.window:.0f} s, '
          f'ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}, {os.cpu_count()} cores, load '
          + ' '.join(f'{value:.1f}' for value in os.getloadavg()))
    if args.markdown:
        print('| ' + ' | '.join(header) + ' |')
        print('|' + '---|' * len(header))
        for row in rows:
            print('| ' + ' | '.join(row) + ' |')
    else:
        widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
        print('  '.join(h.rjust(w) for h, w in zip(header, widths, strict=True)))
        for row in rows:
            print('  '.join(c.rjust(w) for c, w in zip(row, widths, strict=True)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
