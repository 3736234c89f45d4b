# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""``mag_calibrator`` node: raw ``imu/mag`` in, ``imu/mag_corrected`` out, services to calibrate.

Wiring only: declare the parameters, build the ``CalibrationSession`` (every decision is its),
connect the callbacks, publish. Fits run in a worker process, file I/O on a thread. Beside it in
``nodes/``: turning.py, calibration_parameters.py, mag_calibrator_parameters.py, auto_save.py,
location.py (docs/ARCHITECTURE.md).

Subscribed topics (sensor-data QoS: best effort, depth 100):

- ``imu/mag`` (sensor_msgs/MagneticField): the raw field, tesla.
- ``imu/data_raw`` (sensor_msgs/Imu), while ``use_imu``: the accelerometer (and gyroscope) the
  calibration is aligned to, from readings held still; in ``imu/mag``'s frame (samples in
  another are refused: ``pairing.py``).
- ``gps/fix`` (sensor_msgs/NavSatFix): a plausible fix locates the robot for the World
  Magnetic Model when ``latitude``/``longitude`` are NaN and ``use_gps`` holds; one over
  10 km away replaces it (``nodes/location.py``).
- ``imu/temperature`` and ``interference_inputs``: the robot's own field's inputs (inputs.py).

Published topics:

- ``imu/mag_corrected`` (sensor_msgs/MagneticField, reliable, depth 10): the corrected field,
  its covariance carried through the correction; while the calibration in force is judged not
  to fit (state calibrated-misfit) the square of the measured median |B| error is added to each
  variance, so a fusion filter down-weights or gates it; while uncalibrated nothing, or the raw
  message with ``publish_uncalibrated``.
- ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): the calibration's state, once a second;
  WARN while another node publishes ``imu/mag_corrected`` or corrects ``imu/mag`` too.
- ``~/view/raw``, ``~/view/corrected`` (sensor_msgs/PointCloud2) and ``~/view/markers``
  (visualization_msgs/MarkerArray): latched, every ``view_period`` while someone subscribes.
- ``cmd_vel`` (geometry_msgs/Twist, or TwistStamped with ``cmd_vel_stamped``; reliable): only
  while ``~/rotate_and_calibrate`` turns the robot, and its zero after a stop.

Services (seven, all std_srvs/Trigger):

- ``~/calibrate``: fit the buffer now; answers once the fit is in force, or why it is not.
- ``~/save``: write the calibration in force to ``calibration_file``.
- ``~/load``: put the calibration in ``calibration_file`` in force.
- ``~/reset``: empty the buffer, forget a location from gps/fix; the calibration stays.
- ``~/rotate_and_calibrate``: turn in place on ``cmd_vel`` until calibrated (ground robots).
- ``~/stop_rotation``: stop that turn (zero at once).
- ``~/learn_compensation``: learn the robot's own field now, while its motors run through
  several currents (on a stand, or driving straight at several speeds: ArduPilot's compassmot);
  answers once it is in force and stops improving, or after ``compensation_timeout`` with what
  it still needs.

Timers: POLL_PERIOD_S (finished fits and file operations, waiting service answers, auto-save,
``calibration.*``), DIAGNOSTICS_PERIOD_S (progress log line, /diagnostics, RViz view),
COMMAND_PERIOD_S (the turn's command). ``--log-level mag_calibrator:=debug`` logs decisions.

Parameters, by what they set; each one's default, range and meaning are in
``mag_calibrator_parameters.PARAMETERS`` (what ``ros2 param describe`` shows), in
config/mag_calibrator.yaml and in the README's table:

- the fit and its gates: ``buffer_size``, ``k``, ``model``, ``field_strength``,
  ``min_coverage``, ``max_residual_pct``, ``full_scale``;
- when to calibrate: ``auto_calibrate``, ``auto_calibrate_period``, ``refine``,
  ``refine_period``, ``online_tracking``, ``tracking_improvement``,
  ``tracking_max_change_rate``; the robot's own field: ``learn_compensation``,
  ``use_temperature``, ``interference_inputs``, ``compensation_timeout``;
- output, file and views: ``publish_uncalibrated``, ``auto_save``, ``calibration_file``
  ($ROS_HOME/mag_calibrator/<namespace>__<name>.yaml: loaded at start-up and by ~/load,
  written by ~/save), ``progress_log_period``, ``view_period``, ``view_scale``;
- alignment to the IMU and the Earth's field here: ``use_imu``, ``gyro_aided`` (calibrated
  first from the gyroscope's turning), ``max_alignment_deg``,
  ``latitude``, ``longitude``, ``altitude`` (NaN: unknown; one alone waits for the other),
  ``use_gps``, ``max_field_error_pct``, ``max_dip_error_deg``, ``earth_field_gate``;
- turning in place (``~/rotate_and_calibrate``): ``rotation_speed``,
  ``rotation_acceleration``, ``rotation_timeout``, ``cmd_vel_stamped``, ``cmd_vel_frame_id``;
- the calibration in force (set by the node only; given with --params-file at start-up):
  ``calibration.offset``, ``.matrix``, ``.field_strength``, ``.model``, ``.rotation`` and the
  metadata a file carries (``calibration.residual_rms_pct``, ``calibration.coverage`` ...).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import math
from pathlib import Path
import time

import numpy.ma  # noqa: F401 - np.median imports it on first use: at start-up, not in a callback
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.task import Future
from sensor_msgs.msg import Imu, MagneticField, NavSatFix
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.fit.calibration import (
    Calibration,
    CalibrationError,
    transform_covariance,
    with_uncertainty,
)
from mag_calibrator_ros.calibration.fit.earth_field import import_model
from mag_calibrator_ros.calibration.live.pairing import Delivery
from mag_calibrator_ros.calibration.live.report import (
    NodeStatus,
    SessionReport,
    calibration_summary,
    no_input_text,
    no_message_text,
)
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.worker import FitRunner, ProcessRunner
from mag_calibrator_ros.calibration.store.calibration_file import (
    LoadedCalibration,
    default_calibration_path,
    resolve_calibration_path,
    save_calibration,
    try_read_calibration_file,
)
from mag_calibrator_ros.nodes.answers import IoThread, answering
from mag_calibrator_ros.nodes.auto_save import AutoSaveThrottle
from mag_calibrator_ros.nodes.calibration_parameters import (
    CalibrationParameters,
    calibration_from,
    parameters_given,
    shadowed_file_note,
    startup_load_path,
)
from mag_calibrator_ros.nodes.diagnostics import (
    ERROR,
    OK,
    WARN,
    DiagnosticsPublisher,
    diagnostic_status,
)
from mag_calibrator_ros.nodes.graph_watch import GraphWatch
from mag_calibrator_ros.nodes.inputs import (
    InputSubscriptions,
    learning_plan,
    magnetic_field_topics,
)
from mag_calibrator_ros.nodes.location import LOCATION_PARAMETERS, EarthFieldHere
from mag_calibrator_ros.nodes.mag_calibrator_parameters import (
    PARAMETERS,
    parameter_problems,
    session_settings,
)
from mag_calibrator_ros.nodes.parameters import (
    ConfigurationError,
    declare_checked,
    follow_bare_log_level,
    refuse_to_start,
)
from mag_calibrator_ros.nodes.runtime import guarded, spin_node
from mag_calibrator_ros.nodes.turning import TurnInPlace
from mag_calibrator_ros.nodes.view_publisher import ViewPublisher

NODE_NAME = 'mag_calibrator'
DIAGNOSTICS_PERIOD_S = 1.0
POLL_PERIOD_S = 0.05
"""How often finished fits and file operations are collected (service answers wait at most
about this long once the work is done)."""
WINDOW_GRACE, WINDOW_SLACK_S = 1.5, 5.0
"""~/learn_compensation ends by the readings' stamps (``compensation_timeout`` of them); when
they stall, the node ends it itself after 1.5 times as long plus 5 s of its own clock."""
INPUT_QOS = QoSProfile(
    history=qos_profile_sensor_data.history,
    depth=100,  # sensor-data QoS (best effort, REP-2003) with room for bursts at 1 kHz
    reliability=qos_profile_sensor_data.reliability,
    durability=qos_profile_sensor_data.durability,
)


def delivery(info: dict) -> Delivery:
    """When a message was sent, received and (now) handled, from rclpy's MessageInfo."""
    return Delivery(int(info.get('source_timestamp') or 0),
                    int(info.get('received_timestamp') or 0), time.time_ns())


class MagCalibratorNode(Node):
    """Live magnetometer calibration; ``.session`` exposes the engine state (demo, tests)."""

    def __init__(self, *, runner: FitRunner | None = None, **node_kwargs) -> None:
        """``runner``: where fits run (a ``ProcessRunner`` of its own by default; tests and
        benchmarks give one that fails on demand); ``node_kwargs`` go to rclpy's ``Node``."""
        node_kwargs.setdefault('node_name', NODE_NAME)
        super().__init__(**node_kwargs)
        follow_bare_log_level(self)
        self._default_file = default_calibration_path(self.get_fully_qualified_name())
        problems: list[str] = []
        for name, (default, description, extras) in PARAMETERS.items():
            if name == 'calibration_file':
                default = str(self._default_file)
            declare_checked(self, name, default,
                            ParameterDescriptor(description=description, **extras), problems)
        problems += parameter_problems(self._current_values())
        if problems:
            Node.destroy_node(self)  # nothing else was created yet
            refuse_to_start(self, problems)
        self._calibration_parameters = CalibrationParameters(self)
        if runner is None:
            runner = ProcessRunner()
            runner.start()  # the worker imports the fitting stack while the node starts up
        self._settings = session_settings(self._current_values())  # as the session has them
        self.session = CalibrationSession(self._settings, runner=runner)
        self._io = IoThread('mag_calibrator_io')  # file loads, saves, the model
        self._requests: dict[int, Future] = {}  # session tickets waiting for their answer
        self._learning: dict[int, float] = {}  # ~/learn_compensation tickets: wall deadline
        self._problem: str | None = None  # a calibration file/parameter error, shown as ERROR
        self._file_warning: str | None = None  # a refused ~/load beside a calibration in force
        self._last_progress_log = -math.inf
        self._received_at_log = 0  # input messages counted at the last progress line
        self._started = time.monotonic()
        self._auto_save = AutoSaveThrottle()
        self._saved: Calibration | None = None  # last saved to or loaded from the file
        self._imu_subscription = None
        self._earth_here = EarthFieldHere(self, self.session, self._io)  # parameters, gps/fix
        self._graph = GraphWatch()  # another publisher on the output, another calibrator
        import_model()  # now: an import on the I/O thread would hold the lock messages need
        self._startup(self._calibration_parameters.given)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self._calibration_parameters.show(self.session.calibration)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._publisher = self.create_publisher(MagneticField, 'imu/mag_corrected',
                                                QoSProfile(depth=10))
        self.create_subscription(MagneticField, 'imu/mag', guarded(self, 'imu/mag', self._on_mag),
                                 INPUT_QOS)
        self._sync_imu_subscription()
        self.create_subscription(NavSatFix, 'gps/fix',
                                 guarded(self, 'gps/fix', self._earth_here.on_fix), INPUT_QOS)
        self._inputs = InputSubscriptions(self, self.session, lambda: self._settings,
                                          INPUT_QOS)  # imu/temperature ...
        self._earth_here.relocate()
        # Services wait for the fit worker and the I/O thread outside the default (mutually
        # exclusive) group, or the poll timer that completes them could never run.
        waiting = ReentrantCallbackGroup()
        for name, callback in (('~/calibrate', self._on_calibrate), ('~/save', self._on_save),
                               ('~/reset', self._on_reset), ('~/load', self._on_load),
                               ('~/learn_compensation', self._on_learn_compensation)):
            self.create_service(Trigger, name, answering(self, name, callback),
                                callback_group=waiting)
        self._diagnostics = DiagnosticsPublisher(self)
        self._view = ViewPublisher(self, DIAGNOSTICS_PERIOD_S)
        self.create_timer(POLL_PERIOD_S, guarded(self, 'poll', self._on_poll))
        self.create_timer(DIAGNOSTICS_PERIOD_S, guarded(self, 'diagnostics', self._on_tick))
        self._turning = TurnInPlace(self, self.session, self._request_calibration,
                                    lambda name, callback: answering(self, name, callback))
        self._rotation = self._turning.controller  # its state: diagnostics, the progress log

    def destroy_node(self) -> None:
        self._turning.stop_for_shutdown()
        self.session.close()
        self._io.shutdown()
        super().destroy_node()

    # -- parameters ------------------------------------------------------------------------------

    def _current_values(self) -> dict[str, object]:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        refused = self._calibration_parameters.refusal(parameters)
        if refused is not None:
            return refused
        values = self._current_values()
        for parameter in parameters:
            if parameter.name in PARAMETERS:
                values[parameter.name] = parameter.value
        problems = parameter_problems(values, at_run_time=True)
        if problems:
            return SetParametersResult(successful=False, reason='; '.join(problems))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        if any(parameter.name in PARAMETERS for parameter in parameters):
            self._settings = session_settings(self._current_values())
            self.session.reconfigure(self._settings)
            self._inputs.sync()  # in this change: the inputs follow the settings just made
        names = {parameter.name for parameter in parameters}
        in_force = self.session.calibration
        if ('auto_save' in names and self.get_parameter('auto_save').value
                and in_force is not None and in_force is not self._saved):
            self._auto_save.adopted(True)  # turned on: save the calibration in force once
        if 'use_imu' in names:
            self._sync_imu_subscription()
        if names & {*LOCATION_PARAMETERS, 'use_gps'}:
            self._earth_here.relocate()

    # -- start-up --------------------------------------------------------------------------------

    def _calibration_file(self) -> Path:
        return resolve_calibration_path(str(self.get_parameter('calibration_file').value))

    def _startup(self, given: dict[str, object]) -> None:
        """Parameters given with --params-file win (a calibration file that holds another one
        is named); else the file; else run uncalibrated."""
        name = self.get_fully_qualified_name()
        path = startup_load_path(self._calibration_file(), self._default_file, name)
        loaded = try_read_calibration_file(path, name)
        if parameters_given(given):
            try:
                calibration = calibration_from(given)
                problem = self.session.apply_calibration(calibration, 'parameters')
            except (CalibrationError, ValueError, TypeError) as error:
                problem = str(error)
            if problem is not None:
                self._report_problem(f'calibration.* parameters unusable: {problem}')
                return
            self.get_logger().info(
                f'calibration from parameters: {calibration_summary(calibration)}')
            on_file = loaded.calibration if isinstance(loaded, LoadedCalibration) else None
            note = shadowed_file_note(calibration, on_file, path)
            if note is not None and note[0] == 'warning':  # one call site per severity
                self.get_logger().warning(note[1])
            elif note is not None:
                self.get_logger().info(note[1])
            return
        if loaded is None:
            self.get_logger().info(
                f'no calibration file at {path} yet: uncalibrated until ~/calibrate '
                f'(auto_calibrate={self.get_parameter("auto_calibrate").value})')
            return
        self._loaded(path, loaded)

    def _loaded(self, path: Path, loaded: LoadedCalibration | Exception) -> tuple[bool, str]:
        """Put a calibration read from ``path`` in force, or report why it could not be."""
        if not isinstance(loaded, Exception):
            problem = self.session.apply_calibration(loaded.calibration, 'file')
            if problem is not None:
                loaded = CalibrationError(f'{loaded.path}: {problem}')
        if isinstance(loaded, Exception):
            message = f'{loaded}; the calibration in force is unchanged'
            if self.session.calibration is not None:  # it still works: a WARN until fixed
                self._file_warning = message
                self.get_logger().warning(message)
                return False, message
            return False, self._report_problem(
                f'{message} (state {self.session.report().state})')
        for note in loaded.notes:
            self.get_logger().warning(f'{loaded.path}: {note}')
        self._saved = loaded.calibration
        self._problem = self._file_warning = None
        message = f'loaded {loaded.path}: {calibration_summary(loaded.calibration)}'
        self.get_logger().info(message)
        return True, message

    def _report_problem(self, message: str) -> str:
        self._problem = message
        self.get_logger().error(message)
        return message

    # -- stream ----------------------------------------------------------------------------------

    def _on_mag(self, msg: MagneticField, info: dict) -> None:
        field = msg.magnetic_field
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        frame = msg.header.frame_id
        processed = self.session.process(stamp_ns, frame, (field.x, field.y, field.z),
                                         delivery(info))
        if processed.corrected is not None:
            out = MagneticField(header=msg.header)
            out.magnetic_field.x, out.magnetic_field.y, out.magnetic_field.z = (
                processed.corrected.tolist())
            covariance = transform_covariance(processed.calibration.correction,
                                              msg.magnetic_field_covariance)
            out.magnetic_field_covariance = (  # the calibration's own 1-sigma (ErrorModel)
                with_uncertainty(covariance, processed.uncertainty, processed.along)
                if processed.uncertainty > 0.0 else covariance)
            self._publisher.publish(out)
        elif processed.accepted and self.get_parameter('publish_uncalibrated').value:
            self._publisher.publish(msg)
        if processed.accepted:
            self._turning.reading_accepted()
        self._handle_events()

    def _on_imu(self, msg: Imu, info: dict) -> None:
        """O(1): the session keeps the sample to pair magnetometer readings with."""
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        accel, rate = msg.linear_acceleration, msg.angular_velocity
        gyro = None if msg.angular_velocity_covariance[0] == -1.0 else (rate.x, rate.y, rate.z)
        self.session.process_imu(stamp_ns, msg.header.frame_id, (accel.x, accel.y, accel.z),
                                 gyro, delivery(info))

    def _sync_imu_subscription(self) -> None:
        wanted = bool(self.get_parameter('use_imu').value)
        if wanted and self._imu_subscription is None:
            self._imu_subscription = self.create_subscription(
                Imu, 'imu/data_raw', guarded(self, 'imu/data_raw', self._on_imu), INPUT_QOS)
        elif not wanted and self._imu_subscription is not None:
            self.destroy_subscription(self._imu_subscription)
            self._imu_subscription = None

    # -- what the session decided -----------------------------------------------------------------

    def _on_poll(self) -> None:
        """Collect finished fits and file operations; answer waiting services; auto-save;
        show a new calibration in force as calibration.* parameters."""
        self.session.poll()
        if any(time.monotonic() > deadline for deadline in self._learning.values()):
            self.session.end_compensation_window(  # stream time stands still without readings
                'too few magnetometer readings arrived to learn from (is imu/mag published?)')
        self._io.collect()
        self._handle_events()
        if self.session.calibration is not self._calibration_parameters.shown:
            self._calibration_parameters.show(self.session.calibration)
        if self._auto_save.start(time.monotonic()):
            self._io.run(self._save_file).add_done_callback(
                lambda future: self._auto_saved(future.result()))

    def _handle_events(self) -> None:
        logger = self.get_logger()
        for event in self.session.take_events():
            # one call site per severity: rclpy refuses a severity change at the same call site
            if event.level == 'warning':
                logger.warning(event.message)
            elif event.level == 'info':
                logger.info(event.message)
            else:
                logger.debug(event.message)
            if event.adopted:
                self._problem = None
                self._auto_save.adopted(bool(self.get_parameter('auto_save').value))
            self._learning.pop(event.ticket, None)
            request = self._requests.pop(event.ticket, None)
            if request is not None:
                request.set_result(event.attempt)

    def _request_calibration(self, answered: Callable[[Future], None] | None = None) -> Future:
        """Ask the session for a fit; the Future completes with its attempt (``answered``, if
        given, runs as soon as it does)."""
        waiting = Future()
        if answered is not None:
            waiting.add_done_callback(answered)
        self._requests[self.session.request_calibration()] = waiting
        self._handle_events()  # an immediate answer (nothing to wait for)
        return waiting

    # -- services --------------------------------------------------------------------------------

    async def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response):
        attempt = await self._request_calibration()
        response.success, response.message = attempt.success, attempt.message
        return response

    async def _on_learn_compensation(self, request: Trigger.Request,
                                     response: Trigger.Response):
        timeout = float(self.get_parameter('compensation_timeout').value)
        starting, note = learning_plan(self, timeout)
        waiting = Future()
        ticket = self.session.request_compensation(timeout)
        self._requests[ticket] = waiting
        self._learning[ticket] = time.monotonic() + WINDOW_GRACE * timeout + WINDOW_SLACK_S
        self._handle_events()  # a refusal answers at once
        if not waiting.done():
            self.get_logger().info(starting)
        attempt = await waiting
        response.success, response.message = attempt.success, attempt.message
        if note:
            response.message += f' ({note})'
        return response

    def _save_file(self) -> str:
        """On the I/O thread: write the calibration in force (it is immutable)."""
        calibration = self.session.calibration
        if calibration is None:
            raise ValueError('nothing to save: no calibration in force (call ~/calibrate first)')
        written = save_calibration(self._calibration_file(), calibration,
                                   node_name=self.get_fully_qualified_name())
        self._saved, self._file_warning = calibration, None
        return f'saved to {written}'

    def _auto_saved(self, result: object) -> None:
        self._auto_save.finished()
        if isinstance(result, Exception):
            self.get_logger().warning(f'auto_save failed: {result}')
        else:
            self.get_logger().info(f'auto_save: {result}')

    async def _on_save(self, request: Trigger.Request, response: Trigger.Response):
        result = await self._io.run(self._save_file)
        response.success = not isinstance(result, Exception)
        response.message = str(result)
        if response.success:  # one call site per severity (rclpy refuses a change at one)
            self.get_logger().info(response.message)
        else:
            self.get_logger().warning(f'save failed: {result}')
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        self.session.reset()
        forgot = self._earth_here.forget_fix()
        response.success = True
        response.message = (f'buffer emptied; the calibration in force is unchanged '
                            f'(state {self.session.report().state})')
        if forgot:
            response.message += '; the location from gps/fix is forgotten (the next fix locates)'
        self.get_logger().info(response.message)
        return response

    async def _on_load(self, request: Trigger.Request, response: Trigger.Response):
        path = self._calibration_file()
        name = self.get_fully_qualified_name()
        loaded = await self._io.run(lambda: try_read_calibration_file(path, name))
        if loaded is None:
            response.success = False
            response.message = f'no calibration file at {path}; the calibration in force stays'
        else:
            response.success, response.message = self._loaded(path, loaded)
        return response

    # -- once per second -------------------------------------------------------------------------

    def _on_tick(self) -> None:
        """Once a diagnostics period: one report of the session, for the progress line,
        /diagnostics (with what the node adds: the file, the turn, the location) and RViz."""
        now = time.monotonic()
        topic = self.resolve_topic_name('imu/mag')
        values: dict[str, object] = {'calibration_file': str(self._calibration_file()),
                                     **self._rotation.diagnostic_values(now),
                                     **self._earth_here.diagnostic_values()}
        doubled = self._graph.check(self, topic, self._publisher.topic_name)
        warning = '; '.join(text for text in (doubled, self._file_warning) if text)
        no_input = no_input_text(topic, magnetic_field_topics(self, topic))
        report = self.session.report(now, NodeStatus(self._problem, no_input, values, warning))
        self._log_progress(now, report)
        self._publish_diagnostics(topic, report)
        self._publish_view(now, report)

    def _publish_view(self, now: float, report: SessionReport) -> None:
        if not self._view.due(now, float(self.get_parameter('view_period').value)):
            return
        self._view.publish(self.session.view(), report.frame_id or 'imu_link',
                           float(self.get_parameter('view_scale').value))

    def _log_progress(self, now: float, report: SessionReport) -> None:
        period = float(self.get_parameter('progress_log_period').value)
        if period <= 0.0 or report.calibration is not None:
            return
        if self._rotation.state == 'turning':
            return  # the rotation logs its own progress
        if now - self._last_progress_log < period:
            return
        received = report.counts.received
        text = report.progress
        if received == self._received_at_log:  # no message since the last line (or start)
            topic = self.resolve_topic_name('imu/mag')
            text = no_message_text(topic, self.count_publishers(topic), received == 0,
                                   now - self._started, period, magnetic_field_topics(self, topic))
            if text is None:
                return  # discovery takes a moment: no verdict yet
        self._last_progress_log, self._received_at_log = now, received
        self.get_logger().info(text)

    def _publish_diagnostics(self, topic: str, report: SessionReport) -> None:
        # Names and hardware ids carry the namespace: robots on one host stay apart.
        hardware_id = f'{topic} ({report.frame_id})' if report.frame_id else topic
        self._diagnostics.publish([
            diagnostic_status(f'{self.get_fully_qualified_name()}: calibration', hardware_id,
                              {'OK': OK, 'WARN': WARN, 'ERROR': ERROR}[report.level],
                              report.message, dict(report.values))
        ])


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``mag_calibrator`` (also ``ros2 run mag_calibrator_ros mag_calibrator``):
    exit 0 on a normal stop, 2 on invalid parameters."""
    try:  # on Ctrl-C/SIGTERM the node still publishes a final zero on cmd_vel
        return spin_node(MagCalibratorNode, args, publish_on_shutdown=True)
    except ConfigurationError:
        return 2  # already logged as FATAL with every problem


if __name__ == '__main__':
    raise SystemExit(main())
