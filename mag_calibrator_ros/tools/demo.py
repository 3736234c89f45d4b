# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""``mag_calibrator_demo``: the whole live pipeline on a simulated ICM-20948, in one process.

The driver (sim backend, strong hard- and soft-iron distortion, a magnetometer mounted 3 degrees
off the accelerometer) and the calibrator run in one process, each node spun on its own thread
(see NodeThreads), talking over DDS as on a robot, imu/data_raw included. While the simulated
board is turned from tilt to tilt and held still at each (``poses``: what aligning to gravity
needs), a progress bar shows direction coverage and buffer fill; once
coverage suffices the demo asks for a calibration through the real ``~/calibrate`` service,
measures the raw and corrected streams against the simulator's true field (and the alignment it
recovered against the misalignment simulated), saves the file
through ``~/save`` and draws a before/after PNG. Exit status 0 when the calibration succeeded
and everything was written.

``--ground-robot``: the simulated board is a ground robot that turns only as commanded on
``cmd_vel`` (``sim.motion: cmd_vel``, 2° of tilt wobble). The demo calls
``~/rotate_and_calibrate``; the calibrator turns the robot until the heading circle is covered
and the fit passes, then stops it. The demo then turns the robot once more itself (as a teleop
would) to score the heading before and after against the simulator's truth, and drives the
first ``--drive-seconds`` of ``motion.GROUND_COURSE`` (legs at varying speed, turns in place,
stops), showing the heading error of the corrected stream while it drives. The robot has its own
field (``--no-robot-field`` removes it): its battery current puts 8 uT along the chip's x axis
at the full current, and the hard iron drifts 0.2 uT/degC along y while the die warms by 20 degC
(time constant 60 s) from power-on, as benchmarks/bench_interference.py simulates; the heading
error while driving is what the calibrator leaves uncompensated.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
import math
import os
from pathlib import Path
import sys
import threading
import time
from typing import TypeVar

from geometry_msgs.msg import Twist
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.fit.coverage import direction_coverage
from mag_calibrator_ros.calibration.fit.earth_field import location_problems
from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode
from mag_calibrator_ros.nodes.runtime import NodeThreads
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.tools.plotting import plot_calibration

FIELD_UT = 50.0
INCLINATION_DEG = 60.0
HARD_IRON_UT = (120.0, -80.0, 60.0)
SOFT_IRON = (  # symmetric, scales 0.85-1.15, off-diagonals up to 0.12
    1.15, 0.10, -0.08,
    0.10, 0.85, 0.12,
    -0.08, 0.12, 1.00,
)
MISALIGNMENT_DEG = (1.8, -1.9, 1.4)
"""The magnetometer's axes against the accelerometer's (a rotation vector): 3.0 deg."""
NAMESPACE = 'mag_calibrator_demo'
SERVICE_TIMEOUT_S = 60.0
"""How long the demo waits for a service's answer: ~/calibrate answers once its fit has run in the
worker, which a busy or small computer gives little CPU (a user's `ros2 service call` waits as
long as it takes)."""
GROUND_HARD_IRON_UT = (55.0, -45.0, 25.0)
"""75 uT: three times the horizontal field (25 uT at 60 deg inclination)."""
GROUND_WOBBLE_DEG = 2.0
CHECK_TURN_RATE = 0.6
"""rad/s of the demo's own turn that scores the calibration over a full circle."""
ROBOT_FIELD = {  # the robot's own field (issue #26), as benchmarks/bench_interference.py
    'current_field_ut_per_a': [8.0 / motion.DriveCurrent().full_a, 0.0, 0.0],
    'hard_iron_drift_ut_per_c': [0.0, 0.2, 0.0],
    'temperature_c': 20.0, 'temperature_rise_c': 20.0, 'temperature_time_constant_s': 60.0,
}
DRIVE_REPORT_S = 5.0
"""Seconds of driving per line of the heading error shown."""
LEVEL_HORIZONTAL_SHARE = math.cos(math.radians(INCLINATION_DEG))
"""Heading is scored on samples whose true field is at least as horizontal (in the chip x-y
plane) as a level-mounted sensor sees it; near the chip z axis a heading has no meaning."""


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='mag_calibrator_demo',
        description='Live calibration of a simulated ICM-20948 with a strong hard- and soft-iron '
        'distortion: driver + calibrator in one process, calibrate via the service, '
        'before/after errors against the simulator truth, calibration file and PNG.',
    )
    parser.add_argument('--output-dir', default='mag_calibrator_demo_out',
                        help='where calibration.yaml and calibration.png go '
                        '(default: %(default)s)')
    parser.add_argument('--collect-timeout', type=float, default=45.0,
                        help='seconds of tumbling at most before calibrating anyway '
                        '(default: %(default)s)')
    parser.add_argument('--min-coverage', type=float, default=0.8,
                        help='direction coverage (0-1) to reach before calibrating; the '
                        "calibrator's own gate is lower (default: %(default)s)")
    parser.add_argument('--evaluate-seconds', type=float, default=4.0,
                        help='seconds of corrected stream scored against the truth '
                        '(default: %(default)s)')
    parser.add_argument('--buffer-size', type=int, default=None,
                        help="calibrator buffer size (default: the calibrator's)")
    parser.add_argument('--seed', type=int, default=1, help='simulated motion and noise seed')
    parser.add_argument('--ground-robot', action='store_true',
                        help='a ground robot that only turns: the calibrator turns it in place '
                        'through cmd_vel (~/rotate_and_calibrate) and stops it when calibrated')
    parser.add_argument('--robot-field', action=argparse.BooleanOptionalAction, default=True,
                        help='--ground-robot: its battery current and warming die distort the '
                        'field (8 uT at full current, 0.2 uT/degC over 20 degC; default: '
                        '%(default)s)')
    parser.add_argument('--drive-seconds', type=float, default=60.0,
                        help='--ground-robot: seconds of the ground course driven after '
                        'calibrating, the heading error shown (0: none; the course is '
                        f'{motion.CourseDriver().duration_s:.0f} s; default: %(default)s)')
    parser.add_argument('--motion', choices=[kind for kind in motion.TRAJECTORY_KINDS
                                             if kind != 'cmd_vel'], default='poses',
                        help='how the simulated board moves (default: %(default)s: held still '
                        'at one tilt after another, so the calibration is also aligned to the '
                        'accelerometer; tumble never holds still)')
    parser.add_argument('--latitude', type=float, default=None,
                        help='simulate the World Magnetic Model field at this latitude (with '
                        '--longitude) and give the calibrator the location')
    parser.add_argument('--longitude', type=float, default=None)
    args = parser.parse_args(argv)
    if not args.collect_timeout > 0 or not args.evaluate_seconds > 0:
        parser.error('--collect-timeout and --evaluate-seconds must be > 0')
    if not 0.0 <= args.drive_seconds <= motion.CourseDriver().duration_s:
        parser.error(f'--drive-seconds must be within [0, '
                     f'{motion.CourseDriver().duration_s:.0f}] (the ground course)')
    if not 0.0 < args.min_coverage <= 1.0:
        parser.error('--min-coverage must be in (0, 1]')
    if (args.latitude is None) != (args.longitude is None):
        parser.error('give both --latitude and --longitude')
    if args.latitude is not None and location_problems(args.latitude, args.longitude):
        parser.error('; '.join(location_problems(args.latitude, args.longitude)))
    return args


@dataclass(frozen=True)
class ErrorStats:
    """RMS and max of one error measure over the scored samples."""

    rms: float
    max: float

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        if len(errors) == 0:
            return cls(math.nan, math.nan)
        return cls(float(np.sqrt(np.mean(errors**2))), float(np.max(np.abs(errors))))


def direction_errors_deg(vectors: np.ndarray, truth: np.ndarray) -> np.ndarray:
    cosine = np.sum(vectors * truth, axis=1) / (
        np.linalg.norm(vectors, axis=1) * np.linalg.norm(truth, axis=1)
    )
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def heading_errors_deg(vectors: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Azimuth about the chip z axis (a level compass's heading), wrapped to [-180, 180)."""
    horizontal = np.linalg.norm(truth[:, :2], axis=1) / np.linalg.norm(truth, axis=1)
    keep = horizontal >= LEVEL_HORIZONTAL_SHARE - 1e-9
    return azimuth_errors_deg(vectors[keep], truth[keep])


def azimuth_errors_deg(vectors: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Azimuth about the chip z axis of every vector against the truth, wrapped to [-180, 180)
    (a ground robot's z is its yaw axis: every sample has a heading)."""
    difference = (np.arctan2(vectors[:, 1], vectors[:, 0])
                  - np.arctan2(truth[:, 1], truth[:, 0]))
    return np.degrees((difference + np.pi) % (2.0 * np.pi) - np.pi)


def error_table(vectors: np.ndarray, truth: np.ndarray) -> dict[str, ErrorStats]:
    magnitude = (np.linalg.norm(vectors, axis=1) - np.linalg.norm(truth, axis=1)) * 1e6
    return {
        'direction error (deg)': ErrorStats.of(direction_errors_deg(vectors, truth)),
        'heading error (deg)': ErrorStats.of(heading_errors_deg(vectors, truth)),
        'magnitude error (uT)': ErrorStats.of(magnitude),
    }


class DemoObserver(Node):
    """Watches raw and corrected streams and calls the calibrator's services, like a user."""

    def __init__(self, context: Context, namespace: str = NAMESPACE) -> None:
        super().__init__('demo_observer', namespace=namespace, context=context)
        self._lock = threading.Lock()
        self._raw_by_stamp: dict[tuple[int, int], np.ndarray] = {}
        self.raw: list[np.ndarray] = []
        self.pairs: list[tuple[np.ndarray, np.ndarray]] = []  # (raw, corrected)
        self.create_subscription(MagneticField, 'imu/mag', self._on_raw, qos_profile_sensor_data)
        self.create_subscription(
            MagneticField, 'imu/mag_corrected', self._on_corrected, qos_profile_sensor_data
        )
        self.calibrate = self.create_client(Trigger, 'mag_calibrator/calibrate')
        self.save = self.create_client(Trigger, 'mag_calibrator/save')

    @staticmethod
    def _vector(msg: MagneticField) -> np.ndarray:
        return np.array([msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z])

    def _on_raw(self, msg: MagneticField) -> None:
        with self._lock:
            self.raw.append(self._vector(msg))
            self._raw_by_stamp[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = self.raw[-1]
            if len(self._raw_by_stamp) > 1000:
                self._raw_by_stamp.pop(next(iter(self._raw_by_stamp)))

    def _on_corrected(self, msg: MagneticField) -> None:
        """Pair each corrected sample with its raw input: the header is passed through."""
        with self._lock:
            raw = self._raw_by_stamp.get((msg.header.stamp.sec, msg.header.stamp.nanosec))
            if raw is not None:
                self.pairs.append((raw, self._vector(msg)))

    def take_pairs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        with self._lock:
            pairs, self.pairs = self.pairs, []
        return pairs

    def raw_samples(self) -> np.ndarray:
        with self._lock:
            return np.array(self.raw).reshape(-1, 3)

    def call(self, client, timeout_s: float = SERVICE_TIMEOUT_S) -> Trigger.Response | None:
        if not client.wait_for_service(timeout_sec=timeout_s):
            return None
        future = client.call_async(Trigger.Request())
        deadline = time.monotonic() + timeout_s
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.02)
        return future.result() if future.done() else None


ObserverT = TypeVar('ObserverT', bound=DemoObserver)


def progress_bar(coverage: float, fill: int, capacity: int, elapsed: float, width: int = 30
                 ) -> str:
    done = int(round(width * min(max(coverage, 0.0), 1.0)))
    return (f'\r  turning [{"#" * done}{"." * (width - done)}] coverage {100 * coverage:3.0f} %'
            f'  buffer {fill:4d}/{capacity}  {elapsed:4.1f} s ')


def collect(calibrator: MagCalibratorNode, target: float, timeout_s: float) -> float:
    """Show progress until coverage reaches ``target`` and the buffer is full, or time runs out."""
    interactive = sys.stdout.isatty()
    start = time.monotonic()
    last_line = -math.inf
    coverage = 0.0
    capacity = int(calibrator.get_parameter('buffer_size').value)  # the session's buffer size
    while True:
        elapsed = time.monotonic() - start
        samples = calibrator.session.view().raw  # a copy: safe while the executor keeps adding
        coverage = direction_coverage(samples).fraction if len(samples) >= 10 else 0.0
        full = len(samples) >= capacity
        if interactive or elapsed - last_line >= 2.0 or (coverage >= target and full):
            line = progress_bar(coverage, len(samples), capacity, elapsed)
            print(line if interactive else line.strip(), end='' if interactive else '\n',
                  flush=True)
            last_line = elapsed
        if (coverage >= target and full) or elapsed >= timeout_s:
            break
        time.sleep(0.2)
    if interactive:
        print()
    return coverage


def take_true_pairs(observer: DemoObserver, driver: Icm20948DriverNode, raw: list,
                    corrected: list, truth: list) -> None:
    """Append the observer's (raw, corrected) pairs that the simulator knows the true field of
    to ``raw``, ``corrected`` and ``truth``; the others are dropped."""
    for raw_sample, corrected_sample in observer.take_pairs():
        true_field = driver.simulator.truth_for_reading(raw_sample)
        if true_field is not None:
            raw.append(raw_sample)
            corrected.append(corrected_sample)
            truth.append(true_field)


def score(observer: DemoObserver, driver: Icm20948DriverNode, seconds: float, calibration=None):
    """Raw vs truth and corrected vs truth over ``seconds`` of the live corrected stream (and,
    given the calibration, the same corrected without its rotation: what aligning gained)."""
    observer.take_pairs()
    time.sleep(seconds)
    raw, corrected, truth = [], [], []
    take_true_pairs(observer, driver, raw, corrected, truth)
    if not truth:
        return 0, None, None
    truth = np.array(truth)
    after = error_table(np.array(corrected), truth)
    if calibration is not None and calibration.aligned:
        unaligned = calibration.unrotated(np.array(raw))
        after['direction, unaligned (deg)'] = ErrorStats.of(direction_errors_deg(unaligned,
                                                                                 truth))
    return len(truth), error_table(np.array(raw), truth), after


def noise_free_direction_error(calibration, seed: int) -> ErrorStats:
    """The calibration alone, without sensor noise: distorted true fields over all orientations."""
    truth = motion.body_field_samples('tumble', 6000, 100.0, FIELD_UT * 1e-6, INCLINATION_DEG,
                                      seed + 1)
    soft_iron = np.reshape(SOFT_IRON, (3, 3))
    sensed = truth @ misalignment()  # the magnetometer reads A^T @ field
    readings = sensed @ soft_iron.T + np.array(HARD_IRON_UT) * 1e-6
    return ErrorStats.of(direction_errors_deg(calibration.apply(readings), truth))


def print_summary(count: int, before: dict, after: dict) -> None:
    print(f'\nErrors against the simulator truth over {count} live samples '
          '(before = raw imu/mag, after = imu/mag_corrected):')
    print(f'  {"":24s} {"before RMS":>11s} {"before max":>11s} {"after RMS":>10s} '
          f'{"after max":>10s}')
    for name in after:
        b, a = before.get(name, ErrorStats(math.nan, math.nan)), after[name]
        print(f'  {name:24s} {b.rms:11.3f} {b.max:11.3f} {a.rms:10.3f} {a.max:10.3f}')


def answered(service: str, response: Trigger.Response | None) -> int:
    """Print the service's answer. Returns 0 when it succeeded, or the demo's exit status: 2
    when it did not answer, 1 when it refused."""
    if response is None:
        print(f'{service} did not answer', file=sys.stderr)
        return 2
    print(f'{service} -> success={response.success}: {response.message}')
    return 0 if response.success else 1


def summarise_and_save(observer: DemoObserver, count: int, before: dict | None,
                       after: dict | None) -> int:
    """The before/after table, then the file saved through ~/save. Returns 0, or the demo's
    exit status: 3 when no corrected sample could be paired with the truth, 4 when the save
    failed."""
    if count == 0:
        print('no corrected samples could be paired with the truth', file=sys.stderr)
        return 3
    print_summary(count, before, after)
    saved = observer.call(observer.save)
    if saved is None or not saved.success:
        print(f'~/save failed: {saved.message if saved else "no answer"}', file=sys.stderr)
        return 4
    return 0


def output_files(args: argparse.Namespace) -> tuple[Path, Path]:
    """(calibration file, plot) in --output-dir, both removed: the demo starts uncalibrated and
    writes both anew."""
    output_dir = Path(args.output_dir).expanduser().resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    files = output_dir / 'calibration.yaml', output_dir / 'calibration.png'
    for stale in files:
        stale.unlink(missing_ok=True)
    return files


def simulated_board(context: Context, motion_kind: str, hard_iron_ut, seed: int,
                    namespace: str = NAMESPACE, **sim) -> Icm20948DriverNode:
    """The driver on the simulated ICM-20948: the demo's field and soft iron, 100 Hz; ``sim``
    sets further ``sim.*`` parameters by name."""
    overrides = [
        Parameter('backend', value='sim'),
        Parameter('rate_hz', value=100),
        Parameter('sim.field_ut', value=FIELD_UT),
        Parameter('sim.inclination_deg', value=INCLINATION_DEG),
        Parameter('sim.hard_iron_ut', value=list(hard_iron_ut)),
        Parameter('sim.soft_iron', value=list(SOFT_IRON)),
        Parameter('sim.motion', value=motion_kind),
        Parameter('sim.seed', value=seed),
    ] + [Parameter(f'sim.{name}', value=value) for name, value in sim.items()]
    return Icm20948DriverNode(namespace=namespace, context=context,
                              parameter_overrides=overrides)


def misalignment() -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(MISALIGNMENT_DEG)).as_matrix()


def print_alignment(calibration) -> None:
    """The rotation recovered against the one simulated."""
    if not calibration.aligned:
        print('Not aligned to the IMU (no still tilts seen: see the ~/calibrate answer).')
        return
    error = rotation_angle_deg(calibration.rotation @ misalignment().T)
    print(f'Alignment to the IMU: rotation {rotation_angle_deg(calibration.rotation):.2f} deg '
          f'recovered (simulated {rotation_angle_deg(misalignment()):.2f} deg, error '
          f'{error:.3f} deg); dip {calibration.metadata.get("dip_deg", math.nan):.2f} deg '
          f'\u00b1 {calibration.metadata.get("dip_std_deg", math.nan):.2f} deg over '
          f'{calibration.metadata.get("static_samples", 0)} still tilts.')


def start_pipeline(context: Context, args: argparse.Namespace, driver: Icm20948DriverNode,
                   observer_type: type[ObserverT], calibration_file: Path,
                   overrides: Sequence[Parameter] = ()
                   ) -> tuple[MagCalibratorNode, ObserverT, NodeThreads]:
    """The calibrator beside ``driver`` (writing ``calibration_file``, no progress log, the
    --buffer-size asked for, then ``overrides``) and the demo's observer, every node spinning
    on its own thread; the caller shuts the NodeThreads down."""
    parameters = [Parameter('calibration_file', value=str(calibration_file)),
                  Parameter('progress_log_period', value=0.0), *overrides]
    if args.buffer_size is not None:
        parameters.append(Parameter('buffer_size', value=args.buffer_size))
    calibrator = MagCalibratorNode(namespace=NAMESPACE, context=context,
                                   parameter_overrides=parameters)
    observer = observer_type(context)
    spinning = NodeThreads(context)
    for node in (driver, calibrator, observer):
        spinning.add(node)
    return calibrator, observer, spinning


def run(args: argparse.Namespace, context: Context) -> int:
    if args.ground_robot:
        return run_ground(args, context)
    calibration_file, plot_file = output_files(args)

    located = args.latitude is not None
    field = (f"the World Magnetic Model's at {args.latitude}, {args.longitude}" if located
             else f'{FIELD_UT:.0f} uT, inclination {INCLINATION_DEG:.0f} deg')
    print(f'Simulated ICM-20948: field {field}, hard iron {list(HARD_IRON_UT)} uT, soft iron '
          f'{list(SOFT_IRON)} (row-major), magnetometer {rotation_angle_deg(misalignment()):.1f}'
          f' deg off the accelerometer (rotation vector {list(MISALIGNMENT_DEG)} deg).')
    sim = {'mag_misalignment_deg': list(MISALIGNMENT_DEG)}
    overrides = [Parameter('auto_calibrate', value=False)]
    if located:  # the same place for both: the calibrator takes F from the model
        sim.update(latitude=args.latitude, longitude=args.longitude)
        overrides += [Parameter('latitude', value=args.latitude),
                      Parameter('longitude', value=args.longitude)]
    else:
        overrides.append(Parameter('field_strength', value=FIELD_UT * 1e-6))  # the local field
    driver = simulated_board(context, args.motion, HARD_IRON_UT, args.seed, **sim)
    calibrator, observer, spinning = start_pipeline(context, args, driver, DemoObserver,
                                                    calibration_file, overrides)
    try:
        target = args.min_coverage
        print(f'Turn the board through every orientation, holding it still now and then: '
              f'collecting until coverage '
              f'{100 * target:.0f} % (at most {args.collect_timeout:.0f} s).')
        reached = collect(calibrator, target, args.collect_timeout)
        if reached < target:
            print(f'Coverage {100 * reached:.0f} % after {args.collect_timeout:.0f} s, short of '
                  f'the {100 * target:.0f} % asked for (--min-coverage): calibrating with what '
                  'there is; the calibrator gates on its own min_coverage.')

        response = observer.call(observer.calibrate)
        status = answered('~/calibrate', response)
        if status:
            return status

        calibration = calibrator.session.calibration
        print_alignment(calibration)
        print(f'Scoring {args.evaluate_seconds:.0f} s of the corrected stream...')
        count, before, after = score(observer, driver, args.evaluate_seconds, calibration)
        status = summarise_and_save(observer, count, before, after)
        if status:
            return status
        calibration = calibrator.session.calibration
        plot_calibration(observer.raw_samples() * 1e6, calibration.scaled(1e6), plot_file,
                         title='mag_calibrator_demo: simulated ICM-20948', units='uT')
        print(f'\nCalibration file: {calibration_file}\n  (restart with: ros2 run '
              f'mag_calibrator_ros mag_calibrator --ros-args --params-file {calibration_file})')
        print(f'Before/after plot: {plot_file}')
        model_error = noise_free_direction_error(calibration, args.seed)
        print(f'Calibration alone (noise-free readings, every orientation): direction error '
              f'{model_error.rms:.3f} deg RMS, {model_error.max:.3f} deg max; the rest of the '
              f'live error is the sensor noise.')
        direction = after['direction error (deg)']
        print(f'\nDONE: calibrated ({calibration.model}); corrected direction error '
              f'{direction.rms:.2f} deg RMS, {direction.max:.2f} deg max on the live stream.')
        return 0
    finally:
        spinning.shutdown()


class GroundObserver(DemoObserver):
    """The demo's user of a ground robot: the rotation services, and a teleop for a check turn."""

    def __init__(self, context: Context, namespace: str = NAMESPACE) -> None:
        super().__init__(context, namespace)
        self.rotate = self.create_client(Trigger, 'mag_calibrator/rotate_and_calibrate')
        self.stop_rotation = self.create_client(Trigger, 'mag_calibrator/stop_rotation')
        self.teleop = None

    def turn(self, rate: float, speed: float = 0.0) -> None:
        if self.teleop is None:
            self.teleop = self.create_publisher(Twist, 'cmd_vel', 10)
        twist = Twist()
        twist.angular.z = float(rate)
        twist.linear.x = float(speed)
        self.teleop.publish(twist)

    def release(self) -> None:
        """Zero, then leave cmd_vel to others."""
        if self.teleop is not None:
            self.turn(0.0)
            self.teleop.wait_for_all_acked(Duration(seconds=1))
            self.destroy_publisher(self.teleop)
            self.teleop = None


def heading_bar(coverage: float, elapsed: float, state: str, width: int = 30) -> str:
    done = int(round(width * min(max(coverage, 0.0), 1.0)))
    return (f'\r  turning [{"#" * done}{"." * (width - done)}] heading coverage '
            f'{100 * coverage:3.0f} %  {elapsed:5.1f} s  {state:9s}')


def watch_rotation(calibrator: MagCalibratorNode, timeout_s: float) -> float:
    """Show the heading coverage until the rotation has ended; returns the seconds it took."""
    interactive = sys.stdout.isatty()
    start = time.monotonic()
    last_line = -math.inf
    rotation = calibrator._rotation
    while True:
        elapsed = time.monotonic() - start
        coverage = rotation.coverage.fraction if rotation.coverage is not None else 0.0
        if interactive or elapsed - last_line >= 2.0 or rotation.state != 'turning':
            line = heading_bar(coverage, elapsed, rotation.state)
            print(line if interactive else line.strip(), end='' if interactive else '\n',
                  flush=True)
            last_line = elapsed
        if rotation.state != 'turning' or elapsed >= timeout_s:
            break
        time.sleep(0.2)
    if interactive:
        print()
    return time.monotonic() - start


def turn_full_circle(observer: GroundObserver, driver: Icm20948DriverNode, rate: float,
                     timeout_s: float) -> tuple[list, list, list]:
    """Turn the robot one full circle at ``rate`` rad/s (as a teleop would; at most
    ``timeout_s``), pairing each corrected sample with its raw one and the simulator's true
    field; then stop it. Returns (raw, corrected, truth), each a list of (3,) arrays."""
    trajectory = driver.settings.cmd_vel
    start_yaw = trajectory.yaw_and_rate(driver.simulator.sim_time_s)[0]
    observer.take_pairs()
    raw, corrected, truth = [], [], []
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            observer.turn(rate)
            time.sleep(0.05)
            take_true_pairs(observer, driver, raw, corrected, truth)
            yaw = trajectory.yaw_and_rate(driver.simulator.sim_time_s)[0]
            if abs(yaw - start_yaw) >= 2.0 * math.pi:
                break
    finally:
        observer.release()
    return raw, corrected, truth


def check_turn(observer: GroundObserver, driver: Icm20948DriverNode, timeout_s: float):
    """Turn the robot one full circle (the demo as a teleop), pairing the corrected stream with
    the simulator's truth; then stop it. Returns (count, raw errors, corrected errors)."""
    raw, corrected, truth = turn_full_circle(observer, driver, CHECK_TURN_RATE, timeout_s)
    if not truth:
        return 0, None, None
    truth = np.array(truth)
    # heading only: turning cannot tell the vertical field (a planar calibration reports it
    # unobserved), so the corrected magnitude means nothing here
    tables = [{'heading error (deg)': ErrorStats.of(azimuth_errors_deg(np.array(v), truth))}
              for v in (raw, corrected)]
    return len(truth), tables[0], tables[1]


def drive_course(observer: GroundObserver, driver: Icm20948DriverNode, seconds: float
                 ) -> ErrorStats | None:
    """Drive the first ``seconds`` of the ground course (the demo as a teleop, re-sending every
    0.1 s), showing every DRIVE_REPORT_S the heading error of the corrected stream against the
    simulator's truth with the battery current and the die temperature; then stop. Returns the
    heading error over every sample paired while it drove (None: none paired)."""
    course, board = motion.CourseDriver(), driver.simulator.board
    observer.take_pairs()
    everything, window = [], []
    start = time.monotonic()
    next_report = DRIVE_REPORT_S
    print(f'{"s":>5s} {"speed m/s":>9s} {"yaw rad/s":>9s} {"current A":>9s} {"die degC":>8s} '
          f'{"heading error, last 5 s":>24s}')
    try:
        while (into := time.monotonic() - start) < seconds:
            speed, rate = course.command_at(into)
            observer.turn(rate, speed)
            time.sleep(0.1)
            corrected, truth = [], []
            take_true_pairs(observer, driver, [], corrected, truth)
            if truth:
                errors = azimuth_errors_deg(np.array(corrected), np.array(truth)).tolist()
                everything += errors
                window += errors
            if into >= next_report:
                now = driver.simulator.sim_time_s
                shown = (f'{ErrorStats.of(np.array(window)).rms:6.2f} deg RMS' if window
                         else 'no samples')
                print(f'{into:5.0f} {speed:9.2f} {rate:9.2f} '
                      f'{board.battery_current_a(now):9.2f} {board.temperature_c(now):8.1f} '
                      f'{shown:>24s}', flush=True)
                window, next_report = [], next_report + DRIVE_REPORT_S
    finally:
        observer.release()
    return ErrorStats.of(np.array(everything)) if everything else None


def noise_free_heading_error(calibration, driver: Icm20948DriverNode) -> ErrorStats:
    """The calibration alone: its heading over a full turn of the same floor, without noise
    (the robot's own field as it is now, standing: idle current, the die as warm as now)."""
    config = driver.simulator.config
    trajectory = motion.CmdVelTrajectory(seed=config.seed, wobble_deg=GROUND_WOBBLE_DEG)
    earth = motion.earth_field(config.field_ut, config.inclination_deg) * 1e-6
    truth = []
    for t in np.arange(0.0, 30.0, 0.02):
        trajectory.command(CHECK_TURN_RATE, float(t))
        truth.append(trajectory.state(float(t)).rotation.T @ earth)
    truth = np.array(truth)
    offset = driver.simulator.board.hard_iron_ut(driver.simulator.sim_time_s)
    raw = truth @ config.soft_iron_matrix.T + offset * 1e-6
    return ErrorStats.of(azimuth_errors_deg(calibration.apply(raw), truth))


def run_ground(args: argparse.Namespace, context: Context) -> int:
    """--ground-robot: ~/rotate_and_calibrate turns the simulated robot until calibrated."""
    calibration_file, plot_file = output_files(args)
    print(f'Simulated ground robot (ICM-20948 on it): field {FIELD_UT:.0f} uT, inclination '
          f'{INCLINATION_DEG:.0f} deg, hard iron {list(GROUND_HARD_IRON_UT)} uT (3x the '
          f'horizontal field), soft iron {list(SOFT_IRON)}, tilt wobble {GROUND_WOBBLE_DEG} deg; '
          'it drives and turns only as commanded on cmd_vel.')
    robot_field = ROBOT_FIELD if args.robot_field else {}
    if robot_field:
        print(f'Its own field: {ROBOT_FIELD["current_field_ut_per_a"][0]:.2f} uT/A of battery '
              f'current along x (8 uT at the full {motion.DriveCurrent().full_a:.0f} A), the hard '
              f'iron drifting 0.2 uT/degC along y while the die warms 20 -> 40 degC.')
    driver = simulated_board(context, 'cmd_vel', GROUND_HARD_IRON_UT, args.seed,
                             tilt_wobble_deg=GROUND_WOBBLE_DEG, **robot_field)
    calibrator, observer, spinning = start_pipeline(context, args, driver, GroundObserver,
                                                    calibration_file)
    try:
        response = None
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:  # until the first readings have arrived
            response = observer.call(observer.rotate)
            if response is None or response.success or 'no input' not in response.message:
                break
            time.sleep(0.5)
        status = answered('~/rotate_and_calibrate', response)
        if status:
            return status
        took = watch_rotation(calibrator, args.collect_timeout + 120.0)
        reason, message = calibrator._rotation.last_stop or ('', 'still turning')
        print(f'{message}')
        if reason != 'done':
            return 1
        calibration = calibrator.session.calibration
        print(f'Calibrated by turning in place for {took:.1f} s ({calibration.model}).')

        print(f'Turning once more at {CHECK_TURN_RATE} rad/s to score the heading...')
        count, before, after = check_turn(observer, driver, 60.0)
        status = summarise_and_save(observer, count, before, after)
        if status:
            return status
        plot_calibration(observer.raw_samples() * 1e6, calibration.scaled(1e6), plot_file,
                         title='mag_calibrator_demo --ground-robot', units='uT')
        print(f'\nCalibration file: {calibration_file}\nBefore/after plot: {plot_file}')
        own = noise_free_heading_error(calibration, driver)
        die_c = driver.simulator.board.temperature_c(driver.simulator.sim_time_s)
        now = f', standing, the die at {die_c:.1f} degC' if args.robot_field else ''
        print(f'Calibration alone (noise-free readings, a full turn on the same floor{now}): '
              f'heading error {own.rms:.2f} deg RMS, {own.max:.2f} deg max.')
        heading = after['heading error (deg)']
        driving = None
        if args.drive_seconds > 0:
            print(f'\nDriving {args.drive_seconds:.0f} s of the ground course (the corrected '
                  "stream against the truth; no compensation of the robot's own field):")
            driving = drive_course(observer, driver, args.drive_seconds)
            if driving is not None:
                print(f'Heading error while driving (stops included): {driving.rms:.2f} deg RMS, '
                      f'{driving.max:.2f} deg max, before compensation; after: not yet (the '
                      "calibrator does not learn the current's and the temperature's field).")
        print(f'\nDONE: calibrated ({calibration.model}) in {took:.1f} s of turning; corrected '
              f'heading error {heading.rms:.2f} deg RMS, {heading.max:.2f} deg max on the live '
              'stream turning' + (f', {driving.rms:.2f} deg RMS while driving.'
                                  if driving is not None else '.'))
        return 0
    finally:
        spinning.shutdown()


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``mag_calibrator_demo``; returns the exit status."""
    args = parse_args(argv)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    context = Context()
    rclpy.init(args=[], context=context)
    try:
        return run(args, context)
    except KeyboardInterrupt:
        print('\ninterrupted', file=sys.stderr)
        return 130
    finally:
        rclpy.try_shutdown(context=context)


if __name__ == '__main__':
    raise SystemExit(main())
