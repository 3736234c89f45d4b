#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""icm20948_driver (simulated chip) over real DDS: rates, jitter, CPU, I2C load, faults, accuracy.

The driver node runs in its own process (so its CPU share is its own: process time / wall time,
all threads, DDS and the simulator included); this process subscribes to imu/mag, imu/data_raw
and imu/temperature and measures what arrives (header stamps). The node reports its I2C traffic
(wire bytes: address, register and data bytes; bus share = bit times incl. ACK/START/STOP over a
400 kHz clock). Scenarios, in a private ROS_DOMAIN_ID on localhost, magnetometer at 100 Hz:

- mag only: publish_imu and publish_temperature false (accel/gyro off: the AK09916 in bypass);
  every row reports the magnetometer's own wire bytes (BusMonitor share), through the chip's I2C
  master in the IMU rows, on the round clock the driver sets (one round per accel/gyro sample),
  and the samples taken without their copied DRDY;
- IMU 200 Hz and 1 kHz requested (the chip runs 225 Hz and 1125 Hz), nominal;
- the same with sim.i2c_error_rate 0.05;
- a 2 s outage 5 s in (the device comes back power-cycled): rates outside it, recovery time.

Accuracy (in this process, against the simulator's truth): |a| averaged over 1 s lying still;
the gyroscope integrated over 10 s of tumbling / turning versus the true rotation (bias-free).

    python benchmarks/bench_driver.py                  # 30 s per nominal row, 20 s per fault row
    python benchmarks/bench_driver.py --duration 10 --fault-duration 10   # quicker
    python benchmarks/bench_driver.py --master-clocks --duration 10   # the master's clocks only
    python benchmarks/bench_driver.py --fifo --duration 600   # the FIFO, 10 min simulated
"""

from __future__ import annotations

import argparse
import gc
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
MAG_RATE_HZ = 100
OUTAGE_AT_S = 5.0
OUTAGE_S = 2.0
TODAY_POLLS_PER_SAMPLE = 2.5  # before issue #11: a 9-byte ST1..ST2 burst per check
TODAY_MAG_BYTES_PER_S = TODAY_POLLS_PER_SAMPLE * MAG_RATE_HZ * (3 + 9)
TODAY_MAG_BITS_PER_S = TODAY_POLLS_PER_SAMPLE * MAG_RATE_HZ * (9 * (3 + 9) + 3)


def _driver_parameters(imu_rate: int | None, error_rate: float, motion: str = 'tumble',
                       polled: bool = False):
    from rclpy.parameter import Parameter

    parameters = [
        Parameter('backend', value='sim'),
        Parameter('rate_hz', value=MAG_RATE_HZ),
        Parameter('sim.i2c_error_rate', value=error_rate),
        Parameter('sim.seed', value=1),
        Parameter('sim.motion', value=motion),
    ]
    if imu_rate is None:
        parameters += [Parameter('publish_imu', value=False),
                       Parameter('publish_temperature', value=False)]
    else:
        parameters += [Parameter('imu_rate_hz', value=imu_rate),
                       Parameter('imu_fifo', value=not polled)]
    return parameters


def _driver_process(duration_s: float, imu_rate: int | None, error_rate: float,
                    outage: bool, polled: bool = False) -> int:
    """Child: run the node for warm-up + duration; print its own counters and CPU as JSON."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode

    rclpy.init()
    node = Icm20948DriverNode(parameter_overrides=_driver_parameters(imu_rate, error_rate,
                                                                     polled=polled))
    gc.freeze()  # as the console script does (icm20948_driver.started_node)
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
            published0 = (node.published, node.published_imu)
            bus0 = node.supervisor.monitor.counters
            mag_bus0 = node.supervisor.monitor.share('magnetometer')
            measure_from, stop_at = now, now + duration_s
        if outage and outage_start_ros is None and now >= measure_from + OUTAGE_AT_S:
            outage_start_ros = time.time()
            node.simulator.start_outage(OUTAGE_S)
        executor.spin_once(timeout_sec=0.05)
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    bus = node.supervisor.monitor.counters - bus0
    mag_bus = node.supervisor.monitor.share('magnetometer') - mag_bus0
    result = {
        'cpu_share': cpu / wall,
        'published_mag': node.published - published0[0],
        'published_imu': node.published_imu - published0[1],
        'measure_from': time.time() - wall,  # wall-clock (ROS system time) window
        'measure_to': time.time(),
        'bus_bytes_per_s': bus.wire_bytes / wall,
        'bus_share': bus.bits / wall / 400_000,
        'mag_bytes_per_s': mag_bus.wire_bytes / wall,
        'mag_share': mag_bus.bits / wall / 400_000,
        'mag_via_master': node.supervisor.aux_master,
        'master_clock': node.supervisor.master_clock,
        'mag_fallbacks': node.supervisor.mag_fallbacks,
        'i2c_errors': node.i2c_errors,
        'reinitialisations': node.reinitialisations,
        'overruns': node.overruns,
        'imu_resyncs': node.supervisor.imu_resyncs,
        'fifo': node.supervisor.imu_fifo,
        'fifo_faults': [node.supervisor.fifo_overflows, node.supervisor.fifo_resets,
                        node.supervisor.fifo_corrupt],
        'fifo_records_per_read': node.supervisor.fifo_records_per_read,
        'chip_rate_hz': node.settings.imu.odr_hz,
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
    """Receives the driver's topics (reliable, deep queues) on a background executor."""

    TOPICS = ('imu/mag', 'imu/data_raw', 'imu/temperature')

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Imu, MagneticField, Temperature

        rclpy.init()
        self._rclpy = rclpy
        self.node = rclpy.create_node('bench_driver_sink')
        self._stamps: dict[str, list[float]] = {topic: [] for topic in self.TOPICS}
        self._lock = threading.Lock()
        qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
        for topic, kind in zip(self.TOPICS, (MagneticField, Imu, Temperature), strict=True):
            self.node.create_subscription(kind, topic, self._receiver(topic), qos)
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

    def _receiver(self, topic: str):
        def receive(message) -> None:
            with self._lock:
                stamp = message.header.stamp
                self._stamps[topic].append(stamp.sec + 1e-9 * stamp.nanosec)
        return receive

    def take(self) -> dict[str, np.ndarray]:
        with self._lock:
            taken = {topic: np.sort(np.array(stamps)) for topic, stamps in self._stamps.items()}
            self._stamps = {topic: [] for topic in self.TOPICS}
        return taken

    def close(self) -> None:
        self._rclpy.try_shutdown()  # wakes the spinning thread, which then returns
        self._thread.join(timeout=5.0)
        self.node.destroy_node()


def _intervals(stamps: np.ndarray) -> dict[str, float]:
    intervals = np.diff(stamps) * 1e3
    if len(intervals) == 0:
        return {'jitter_ms': math.nan, 'p99_ms': math.nan, 'max_gap_ms': math.nan}
    return {'jitter_ms': float(np.std(intervals)), 'p99_ms': float(np.percentile(intervals, 99)),
            'max_gap_ms': float(np.max(intervals))}


def run_scenario(sink: _Sink, name: str, duration_s: float, imu_rate: int | None,
                 error_rate: float = 0.0, outage: bool = False, polled: bool = False) -> dict:
    command = [sys.executable, __file__, '--driver-process', '--duration', str(duration_s),
               '--error-rate', str(error_rate)]
    command += ['--polled'] if polled else []
    command += ['--imu-rate', str(imu_rate)] if imu_rate is not None else []
    command += ['--outage'] if outage else []
    child = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == 'READY', 'driver process failed to start'
    deadline = time.monotonic() + 30.0
    while len(sink.take()['imu/mag']) == 0 and time.monotonic() < deadline:  # discovery done
        time.sleep(0.1)
    output, _ = child.communicate('GO\n', timeout=duration_s + 90)
    if child.returncode != 0:
        raise RuntimeError(f'{name}: driver process exited {child.returncode}')
    result = json.loads(next(line for line in output.splitlines()
                             if line.startswith('RESULT '))[len('RESULT '):])
    time.sleep(0.2)
    received = sink.take()
    window = result['measure_to'] - result['measure_from']
    span = (result['measure_from'], result['measure_to'])
    stamps = {topic: s[(s >= span[0]) & (s <= span[1])] for topic, s in received.items()}
    rate_window = window
    outside = stamps
    row = {'scenario': name, 'imu_requested': imu_rate,
           'chip_rate_hz': result['chip_rate_hz'] if imu_rate is not None else math.nan}
    if outage and result['outage_start'] is not None:
        start, end = result['outage_start'], result['outage_start'] + OUTAGE_S
        outside = {topic: s[(s < start) | (s >= end)] for topic, s in stamps.items()}
        rate_window = window - OUTAGE_S
        after = [s[s >= end] for s in stamps.values() if len(s[s >= end])]
        row['recovery_s'] = min(float(s[0] - end) for s in after) if after else math.inf
        row['in_outage'] = sum(int(np.count_nonzero((s > start + 0.001) & (s < end)))
                               for s in stamps.values())
    row.update({
        'mag_hz': len(outside['imu/mag']) / rate_window,
        'imu_hz': len(outside['imu/data_raw']) / rate_window,
        'temperature_hz': len(outside['imu/temperature']) / rate_window,
        'mag': _intervals(stamps['imu/mag']),
        'imu': _intervals(stamps['imu/data_raw']),
        'cpu_pct': 100.0 * result['cpu_share'],
        'bus_bytes_per_s': result['bus_bytes_per_s'],
        'bus_pct': 100.0 * result['bus_share'],
        'mag_bytes_per_s': result['mag_bytes_per_s'],
        'mag_bus_pct': 100.0 * result['mag_share'],
        'mag_via_master': result['mag_via_master'],
        'master_clock': result['master_clock'],
        'mag_fallbacks': result['mag_fallbacks'],
        'i2c_errors': result['i2c_errors'],
        'reinits': result['reinitialisations'],
        'overruns': result['overruns'],
        'imu_resyncs': result['imu_resyncs'],
        'fifo': result['fifo'],
        'fifo_faults': result['fifo_faults'],
        'fifo_records_per_read': result['fifo_records_per_read'],
    })
    return row


def _fmt(value: float, spec: str) -> str:
    return '—' if value is None or (isinstance(value, float) and math.isnan(value)) else \
        format(value, spec)


def print_table(rows: list[dict]) -> None:
    print('| scenario | imu/data_raw Hz (req → chip) | imu/mag Hz | imu jitter / p99 / max gap ms '
          '| mag jitter / p99 ms | CPU % | I2C B/s | of which mag | bus % | I2C errors '
          '| re-inits |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|')
    for row in rows:
        imu = (f"{row['imu_hz']:.1f} ({row['imu_requested']} → {row['chip_rate_hz']:.0f})"
               if row['imu_requested'] else '—')
        timing = row['imu']
        imu_timing = (f"{_fmt(timing['jitter_ms'], '.2f')} / {_fmt(timing['p99_ms'], '.1f')} / "
                      f"{_fmt(timing['max_gap_ms'], '.0f')}" if row['imu_requested'] else '—')
        print(f"| {row['scenario']} | {imu} | {row['mag_hz']:.2f} | {imu_timing} | "
              f"{_fmt(row['mag']['jitter_ms'], '.2f')} / {_fmt(row['mag']['p99_ms'], '.1f')} | "
              f"{row['cpu_pct']:.1f} | {row['bus_bytes_per_s']:.0f} | "
              f"{row['mag_bytes_per_s']:.0f} "
              f"({'master' if row['mag_via_master'] else 'bypass'}) | "
              f"{row['bus_pct']:.1f} | "
              f"{row['i2c_errors']} | {row['reinits']} |")


# --- the magnetometer's path at each master clock (simulated time) ------------------------------

class _SimClock:
    """Simulated time: the supervisor is stepped to each poll it asks for, nothing else runs."""

    now = 1000.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, dt: float) -> None:
        self.now += dt


def master_clocks(seconds: float) -> int:
    """The supervisor (driver and simulator, no ROS) on a simulated clock stepped to each poll it
    asks for, at each I2C master clock it can run and in bypass: the magnetometer's wire bytes
    per sample, samples taken without their copied DRDY, samples lost, with no machine load."""
    from mag_calibrator_ros.icm20948.driver import ImuSettings
    from mag_calibrator_ros.icm20948.supervisor import Icm20948Supervisor, ImuSample, MagSample
    from mag_calibrator_ros.sim.config import SimConfig
    from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

    print(f'magnetometer {MAG_RATE_HZ} Hz through each I2C master clock, {seconds:g} s simulated '
          f'after 1 s:')
    print('| IMU (chip) | path / master clock | mag Hz | mag bytes / sample | without DRDY | '
          'lost | IMU Hz |')
    print('|---|---|---:|---:|---:|---:|---:|')
    for imu_rate in (200, 1000):
        for via_master, odr_config in ((True, None), (True, 0), (True, 3), (False, None)):
            clock = _SimClock()
            sim = SimulatedIcm20948Bus(SimConfig(seed=1), clock=clock)
            supervisor = Icm20948Supervisor(
                lambda sim=sim: sim, imu=ImuSettings(rate_hz=imu_rate), clock=clock,
                sleep=clock.sleep, stamp=clock, mag_via_master=via_master,
                master_odr_config=odr_config)
            if via_master and not supervisor.aux_master:
                continue  # this clock cannot carry 100 Hz at this IMU rate (master_plan)
            samples: list = []

            def advance(duration: float, supervisor=supervisor, samples=samples,
                        clock=clock) -> None:
                end = clock.now + duration
                while clock.now < end:
                    clock.now = max(clock.now, min(supervisor.next_due(), end)) + 20e-6
                    samples.extend(supervisor.step())

            advance(1.0)
            mag0 = sum(isinstance(x, MagSample) for x in samples)
            imu0 = sum(isinstance(x, ImuSample) for x in samples)
            bytes0 = supervisor.monitor.share('magnetometer').wire_bytes
            measured0, fallbacks0 = sim.samples_measured, supervisor.mag_fallbacks
            advance(seconds)
            mag = sum(isinstance(x, MagSample) for x in samples) - mag0
            imu = sum(isinstance(x, ImuSample) for x in samples) - imu0
            wire = supervisor.monitor.share('magnetometer').wire_bytes - bytes0
            lost = sim.samples_measured - measured0 - mag
            path = supervisor.master_clock if via_master else 'bypass'
            print(f'| {imu_rate} ({supervisor.imu_settings.odr_hz:.0f} Hz) | {path} | '
                  f'{mag / seconds:.2f} | {wire / max(mag, 1):.2f} | '
                  f'{supervisor.mag_fallbacks - fallbacks0} | {lost} | {imu / seconds:.1f} |')
    return 0


# --- the FIFO on a simulated clock (issue #48) ---------------------------------------------------

FIFO_CHUNK_S = 5.0  # checked against the truth this often (the simulator keeps 16384 truths)


def fifo_stream(seconds: float, imu_rate: int = 1000) -> int:
    """The supervisor reading the FIFO (no ROS, no machine load): ``seconds`` of stream at the
    chip's rate for ``imu_rate`` with the magnetometer at 100 Hz, every published inertial
    sample matched to the simulator's truth by its exact counts (lost, duplicated, corrupt),
    the stamps' spacing against the chip's period and their error against the true sample
    times; then each fault once (an overflow from a 100 ms stall, a torn read, a corrupt
    record, 1 and 2 bytes lost), its count and how long until samples flow again."""
    from mag_calibrator_ros.icm20948.driver import ImuSettings
    from mag_calibrator_ros.icm20948.supervisor import Icm20948Supervisor, ImuSample, MagSample
    from mag_calibrator_ros.sim.config import SimConfig
    from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

    clock = _SimClock()
    start = clock.now
    sim = SimulatedIcm20948Bus(SimConfig(seed=11), clock=clock)
    supervisor = Icm20948Supervisor(
        lambda: sim, imu=ImuSettings(rate_hz=imu_rate), clock=clock, sleep=clock.sleep,
        stamp=clock, stamp_ago=lambda age: clock() - age, imu_fifo=True)
    period = 1.0 / supervisor.imu_settings.odr_hz

    def advance(duration: float) -> list:
        out, end = [], clock.now + duration
        while clock.now < end:
            clock.now = max(clock.now, min(supervisor.next_due(), end)) + 20e-6
            out.extend(supervisor.step())
        return out

    advance(1.0)
    totals = dict(published=0, measured=0, corrupt=0, duplicated=0, mag=0, mag_measured=0)
    worst_spacing = worst_error = 0.0
    last_stamp = None
    for _ in range(max(1, round(seconds / FIFO_CHUNK_S))):
        measured, mag_measured = sim.imu_samples_measured, sim.samples_measured
        delivered = sim.imu_samples_read
        out = advance(FIFO_CHUNK_S)
        imu = [x for x in out if isinstance(x, ImuSample)]
        truths = sim.imu_truths_read()[-(sim.imu_samples_read - delivered):] \
            if sim.imu_samples_read > delivered else []
        order = {id(t): i for i, t in enumerate(truths)}
        positions = [order.get(id(sim.imu_truth_for_reading(
            x.reading.linear_acceleration, x.reading.angular_velocity))) for x in imu]
        totals['corrupt'] += sum(p is None for p in positions)
        found = [p for p in positions if p is not None]
        totals['duplicated'] += len(found) - len(set(found))
        totals['published'] += len(imu)
        totals['measured'] += sim.imu_samples_measured - measured
        totals['mag'] += sum(isinstance(x, MagSample) for x in out)
        totals['mag_measured'] += sim.samples_measured - mag_measured
        stamps = np.array(([last_stamp] if last_stamp is not None else [])
                          + [x.stamp for x in imu])
        worst_spacing = max(worst_spacing, float(np.max(np.abs(np.diff(stamps) - period))))
        last_stamp = stamps[-1]
        errors = [x.stamp - start - truths[p].sample_time
                  for x, p in zip(imu, positions, strict=True) if p is not None]
        worst_error = max(worst_error, float(np.max(np.abs(errors))))
    left = sim.fifo.count // 14
    print(f'FIFO, IMU {imu_rate} ({1 / period:.0f} Hz) and magnetometer {MAG_RATE_HZ} Hz '
          f'({supervisor.master_clock}), {seconds:g} s simulated after 1 s:')
    print(f"  IMU: {totals['published']} published of {totals['measured']} measured "
          f"({totals['measured'] - totals['published'] - left} lost, {left} still in the FIFO), "
          f"{totals['duplicated']} duplicated, {totals['corrupt']} corrupt; FIFO overflows "
          f'{supervisor.fifo_overflows}, resets {supervisor.fifo_resets}, corrupt '
          f'{supervisor.fifo_corrupt}; {supervisor.fifo_records_per_read:.2f} records a read')
    print(f'  stamps: spacing within {100 * worst_spacing / period:.4f} % of the '
          f'{1e3 * period:.4f} ms period; within {1e3 * worst_error:.3f} ms '
          f'({100 * worst_error / period:.1f} % of it) of the true sample times')
    print(f"  magnetometer: {totals['mag']} published of {totals['mag_measured']} measured, "
          f'{supervisor.mag_fallbacks} without DRDY; bus '
          f'{supervisor.monitor.counters.wire_bytes / (clock.now - start):.0f} wire bytes/s')
    print('  | fault | counted as | samples again after (ms of stream) | corrupt published |')
    print('  |---|---|---:|---:|')
    faults = (('overflow: 100 ms stall', lambda: setattr(clock, 'now', clock.now + 0.1)),
              ('torn read after 5 bytes', lambda: sim.tear_next_fifo_read(5)),
              ('1 byte lost', lambda: sim.corrupt_fifo(1)),
              ('corrupt record (2 lost, 2 junk)', lambda: sim.corrupt_fifo(2, 2)))
    for name, inject in faults:
        advance(0.5)
        clock.now += 0.003  # records wait in the FIFO
        counts = (supervisor.fifo_overflows, supervisor.fifo_resets, supervisor.fifo_corrupt)
        inject()
        fault_at = clock.now
        out = [x for x in advance(0.2) if isinstance(x, ImuSample)]
        delivered = sim.imu_truths_read()[-300:]
        order = {id(t) for t in delivered}
        corrupt = sum(id(sim.imu_truth_for_reading(x.reading.linear_acceleration,
                                                   x.reading.angular_velocity)) not in order
                      for x in out)
        again = next((x.stamp for x in out if x.stamp > fault_at + 0.001), math.nan)
        now = (supervisor.fifo_overflows, supervisor.fifo_resets, supervisor.fifo_corrupt)
        counted = ', '.join(f'{label} +{b - a}' for label, a, b in zip(
            ('overflows', 'resets', 'corrupt'), counts, now, strict=True) if b != a)
        print(f'  | {name} | {counted or "nothing"} | {1e3 * (again - fault_at):.1f} | '
              f'{corrupt} |')
    return 0


# --- accuracy against the simulator's truth (in this process) -----------------------------------

def _collect(imu_rate: int, motion: str, seconds: float, warmup_s: float = 1.0):
    """Run the node in this process for ``seconds``; return it and the Imu messages it published.

    The messages are taken where the node publishes them (a tap on its publisher): a subscriber
    in this process would compete with the driver's thread for the interpreter, which is not what
    the accuracy measures. Rates over DDS are the table's business.
    """
    import rclpy
    from rclpy.context import Context

    from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode
    from mag_calibrator_ros.nodes.runtime import NodeThreads

    context = Context()
    rclpy.init(context=context)
    threads = NodeThreads(context)
    node = Icm20948DriverNode(context=context, parameter_overrides=_driver_parameters(
        imu_rate, 0.0, motion))
    gc.freeze()  # as the console script does (icm20948_driver.started_node)
    messages: list = []
    publisher = node._imu_publisher
    publish = publisher.publish

    def tap(message) -> None:
        messages.append(message)
        publish(message)

    publisher.publish = tap
    threads.add(node)
    time.sleep(warmup_s)
    messages.clear()
    time.sleep(seconds)
    node._stop.set()  # freeze the simulator's truth log
    node._pump.join()
    return node, list(messages), (threads, context)


def _close(handles) -> None:
    import rclpy

    threads, context = handles
    threads.shutdown()
    rclpy.try_shutdown(context=context)


def _vectors(messages, field: str) -> np.ndarray:
    return np.array([[getattr(m, field).x, getattr(m, field).y, getattr(m, field).z]
                     for m in messages])


def accel_at_rest(imu_rate: int) -> dict:
    _, messages, handles = _collect(imu_rate, 'still', 1.0)
    try:
        accel = _vectors(messages, 'linear_acceleration')
        return {'imu_rate': imu_rate, 'samples': len(accel),
                'norm_of_mean': float(np.linalg.norm(accel.mean(axis=0))),
                'mean_of_norms': float(np.linalg.norm(accel, axis=1).mean())}
    finally:
        _close(handles)


def gyro_integration(imu_rate: int, motion: str, seconds: float = 10.0) -> dict:
    """Integrate the published rates over ``seconds``; compare with the true rotation between the
    first and last sample's true orientations. dt from header stamps (what a user has) and from
    the simulator's true sample times (the driver's share alone)."""
    from scipy.spatial.transform import Rotation

    node, messages, handles = _collect(imu_rate, motion, seconds)
    try:
        rates = _vectors(messages, 'angular_velocity')
        truths = node.simulator.imu_truths_read()[-len(messages):]  # each read is published once
        assert len(truths) == len(messages)
        stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in messages])
        sample_times = np.array([t.sample_time for t in truths])
        true_delta = Rotation.from_matrix(truths[0].rotation.T @ truths[-1].rotation)
        errors = {}
        for name, times in (('stamps', stamps), ('sample_times', sample_times)):
            for rule, step_rates in (('rectangle', rates[:-1]),
                                     ('trapezoid', 0.5 * (rates[:-1] + rates[1:]))):
                steps = Rotation.from_rotvec(step_rates * np.diff(times)[:, None])
                integrated = Rotation.identity()
                for step in steps:
                    integrated = integrated * step
                errors[f'{rule}_{name}'] = float(
                    np.degrees((true_delta.inv() * integrated).magnitude()))
        expected = (sample_times[-1] - sample_times[0]) * node.settings.imu.odr_hz + 1
        return {'imu_rate': imu_rate, 'motion': motion, 'samples': len(rates),
                'missing': int(round(expected)) - len(rates),
                'span_s': float(sample_times[-1] - sample_times[0]),
                'rotation_deg': float(np.degrees(true_delta.magnitude())), **errors}
    finally:
        _close(handles)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--duration', type=float, default=30.0, help='nominal rows (s)')
    parser.add_argument('--fault-duration', type=float, default=20.0, help='fault rows (s)')
    parser.add_argument('--skip-accuracy', action='store_true')
    parser.add_argument('--master-clocks', action='store_true',
                        help='only the magnetometer path at each I2C master clock, on a '
                             'simulated clock (no ROS, no machine load in the numbers)')
    parser.add_argument('--load', type=int, default=0,
                        help='run this many `yes > /dev/null` beside the node rows (issue #48: '
                             'one per core)')
    parser.add_argument('--rows', default='',
                        help='scenario names to run, separated by ; (default: all)')
    parser.add_argument('--fifo', action='store_true',
                        help='only the FIFO on a simulated clock: --duration s of 1125 Hz '
                             'stream checked against the truth, then its faults')
    parser.add_argument('--driver-process', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--imu-rate', type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument('--error-rate', type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument('--outage', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--polled', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.driver_process:
        return _driver_process(args.duration, args.imu_rate, args.error_rate, args.outage,
                               args.polled)
    if args.master_clocks:
        return master_clocks(args.duration)
    if args.fifo:
        return fifo_stream(args.duration)

    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(101, 180)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    scenarios = [  # name, duration, IMU rate, I2C error rate, outage, polled
        ('mag only', args.duration, None, 0.0, False, False),
        ('IMU 200 Hz', args.duration, 200, 0.0, False, False),
        ('IMU 1 kHz', args.duration, 1000, 0.0, False, False),
        ('IMU 1 kHz, polled', args.duration, 1000, 0.0, False, True),
        ('IMU 200 Hz, 5 % I2C errors', args.fault_duration, 200, 0.05, False, False),
        ('IMU 1 kHz, 5 % I2C errors', args.fault_duration, 1000, 0.05, False, False),
        (f'IMU 200 Hz, {OUTAGE_S:g} s outage', args.fault_duration, 200, 0.0, True, False),
    ]
    wanted = {name.strip() for name in args.rows.split(';') if name.strip()}
    sink = _Sink()
    hogs = [subprocess.Popen(['yes'], stdout=subprocess.DEVNULL) for _ in range(args.load)]
    try:
        rows = [run_scenario(sink, name, duration, rate, errors, outage, polled)
                for name, duration, rate, errors, outage, polled in scenarios
                if not wanted or name in wanted]
    finally:
        sink.close()
        for hog in hogs:
            hog.kill()
    print(f'\nicm20948_driver, sim backend, magnetometer {MAG_RATE_HZ} Hz, ROS_DOMAIN_ID '
          f"{os.environ['ROS_DOMAIN_ID']}; rates received, from header stamps (outage row: "
          f'outside the outage); CPU of the node process (simulator included); I2C wire bytes/s '
          f'and share of a 400 kHz bus.\n')
    print_table(rows)
    if args.load:
        print(f'(with {args.load} `yes > /dev/null` beside it)')
    outage_row = rows[-1]
    if 'recovery_s' in outage_row:
        print(f"\noutage row: recovery {outage_row['recovery_s']:.2f} s after the device is "
              f"back; messages stamped inside the outage: {outage_row.get('in_outage')}")
    before_pct = 100 * TODAY_MAG_BITS_PER_S / 400_000
    print(f'magnetometer polling (its own wire bytes; before issue #11: '
          f'{TODAY_MAG_BYTES_PER_S:.0f} B/s, {before_pct:.2f} % of the bus, a 9-byte burst '
          f'{TODAY_POLLS_PER_SAMPLE:g}x per sample):')
    for row in rows:
        print(f"  {row['scenario']}: {row['mag_bytes_per_s']:.0f} B/s "
              f"({row['mag_bus_pct']:.2f} %), {row['mag_bytes_per_s'] / TODAY_MAG_BYTES_PER_S:.2f}"
              f" of before, {'I2C master' if row['mag_via_master'] else 'bypass'}")
    for row in rows:
        print(f"  {row['scenario']}: temperature {row['temperature_hz']:.1f} Hz, overruns "
              f"{row['overruns']}, imu resyncs {row['imu_resyncs']}, "
              + (f"FIFO overflows/resets/corrupt {'/'.join(map(str, row['fifo_faults']))}, "
                 f"{row['fifo_records_per_read']:.2f} records a read, " if row['fifo'] else
                 'polled, ')
              + f"magnetometer samples "
              f"without DRDY {row['mag_fallbacks']}, I2C master clock {row['master_clock']}")
    if args.skip_accuracy:
        return 0
    print('\nAccuracy against the simulator truth (node in this process, its published Imu '
          'messages):')
    for rate in (200, 1000):
        rest = accel_at_rest(rate)
        print(f"  still, IMU {rate} Hz, 1 s ({rest['samples']} samples): |mean a| = "
              f"{rest['norm_of_mean']:.4f} m/s^2, mean |a| = {rest['mean_of_norms']:.4f} m/s^2")
    print('  gyro integrated over 10 s, rotation error in deg: trapezoid / forward rectangle, '
          'dt from header stamps | from the true sample times')
    for rate in (200, 1000):
        for motion in ('yaw', 'tumble'):
            r = gyro_integration(rate, motion)
            print(f"  {motion}, IMU {rate} Hz, {r['span_s']:.1f} s, {r['samples']} samples "
                  f"({r['missing']} missing), true rotation {r['rotation_deg']:.1f} deg: "
                  f"{r['trapezoid_stamps']:.3f} / {r['rectangle_stamps']:.3f} | "
                  f"{r['trapezoid_sample_times']:.3f} / {r['rectangle_sample_times']:.3f}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
