"""``mag_calibrator`` node: raw ``imu/mag`` in, ``imu/mag_corrected`` out, services to calibrate.

Wiring only: parameters, the subscriptions (``imu/mag``; ``imu/data_raw`` and ``gps/fix`` when
present), the publisher, four std_srvs/Trigger services, a poll timer and the diagnostics timer.
Every decision (screening, buffer, when to fit and whether to adopt, misfit detection, online
tracking, alignment to the IMU, progress text) lives in
:class:`~mag_calibrator_ros.calibration.live.session.CalibrationSession`; its fits run in a worker
process (``ProcessRunner``) and file I/O on a thread, so the message callback never waits for
either.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields
import inspect
import math
from pathlib import Path
from queue import SimpleQueue
import time
import traceback

from geometry_msgs.msg import Twist, TwistStamped
import numpy.ma  # noqa: F401 - np.median imports it on first use: 30 ms in a callback otherwise
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.task import Future
from sensor_msgs.msg import Imu, MagneticField, NavSatFix, NavSatStatus
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.fit.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.fit.coverage import Coverage
from mag_calibrator_ros.calibration.fit.earth_field import (
    EarthField,
    EarthFieldError,
    earth_field,
    location_problems,
)
from mag_calibrator_ros.calibration.live.report import calibration_summary
from mag_calibrator_ros.calibration.live.session import CalibrationSession, transform_covariance
from mag_calibrator_ros.calibration.live.settings import FITTABLE_MODELS, SessionSettings
from mag_calibrator_ros.calibration.live.turning import (
    COMMAND_PERIOD_S,
    MAX_SPEED,
    RotationController,
    RotationSettings,
)
from mag_calibrator_ros.calibration.live.worker import ProcessRunner
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    CalibrationFileMissingError,
    LoadedCalibration,
    calibration_from_parameters,
    calibration_parameters,
    default_calibration_path,
    default_load_path,
    read_calibration_file,
    resolve_calibration_path,
    save_calibration,
)
from mag_calibrator_ros.nodes.diagnostics import (
    ERROR,
    OK,
    WARN,
    DiagnosticsPublisher,
    diagnostic_status,
)
from mag_calibrator_ros.nodes.parameters import (
    ConfigurationError,
    declare_checked,
    refuse_to_start,
)
from mag_calibrator_ros.nodes.runtime import guarded, spin_node
from mag_calibrator_ros.nodes.view import ViewPublisher

NODE_NAME = 'mag_calibrator'
DIAGNOSTICS_PERIOD_S = 1.0
POLL_PERIOD_S = 0.05
"""How often finished fits and file operations are collected (service answers wait at most
about this long once the work is done)."""
AUTO_SAVE_MIN_INTERVAL_S = 10.0
"""auto_save writes at most this often; a calibration adopted meanwhile is saved afterwards."""
INPUT_QOS = QoSProfile(
    history=qos_profile_sensor_data.history,
    depth=100,  # sensor-data QoS (best effort, REP-2003) with room for bursts at 1 kHz
    reliability=qos_profile_sensor_data.reliability,
    durability=qos_profile_sensor_data.durability,
)
DEFAULTS = SessionSettings()
ROTATION_DEFAULTS = RotationSettings()
COMMAND_TOPIC = 'cmd_vel'
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
"""Reliable: a stop must arrive (a best-effort subscriber still matches and gets the re-sends)."""
SHUTDOWN_ACK_S = 0.5
"""On shutdown, wait at most this long for subscribers to acknowledge the final zero."""


def _float_range(low: float, high: float) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]


def _int_range(low: int, high: int) -> list[IntegerRange]:
    return [IntegerRange(from_value=int(low), to_value=int(high), step=1)]


# name: (default, description, descriptor extras). Session settings share their field names.
PARAMETERS: dict[str, tuple[object, str, dict]] = {
    'buffer_size': (DEFAULTS.buffer_size,
                    'Samples kept by the kNN uniqueness buffer (the fit input).',
                    {'integer_range': _int_range(10, 5000)}),
    'k': (DEFAULTS.k, 'Neighbours in the uniqueness score (must be < buffer_size).',
          {'integer_range': _int_range(1, 64)}),
    'model': (DEFAULTS.model, f"Fit model: {', '.join(FITTABLE_MODELS)}.",
              {'additional_constraints': f"one of {', '.join(FITTABLE_MODELS)}"}),
    'field_strength': (DEFAULTS.field_strength,
                       'Local earth field in tesla that |corrected| should have; '
                       '0 keeps the fitted mean radius.',
                       {'floating_point_range': _float_range(0.0, 1e-3)}),
    'min_coverage': (DEFAULTS.min_coverage,
                     'Share of direction cells the buffer must cover before a fit is accepted.',
                     {'floating_point_range': _float_range(0.0, 1.0)}),
    'max_residual_pct': (DEFAULTS.max_residual_pct,
                         'Largest accepted RMS magnitude residual, % of the field.',
                         {'floating_point_range': _float_range(0.01, 100.0)}),
    'full_scale': (DEFAULTS.full_scale,
                   'Tesla; a component at or beyond it is saturated and refused (0 = no check).',
                   {'floating_point_range': _float_range(0.0, 1.0)}),
    'auto_calibrate': (DEFAULTS.auto_calibrate,
                       'Calibrate by itself while uncalibrated, and anew when the calibration in '
                       'force no longer fits the live data.', {}),
    'auto_calibrate_period': (DEFAULTS.auto_calibrate_period,
                              'Seconds (of message stamps) between automatic fits that failed '
                              'their gates.',
                              {'floating_point_range': _float_range(0.5, 3600.0)}),
    'refine': (DEFAULTS.refine,
               'After calibrating, keep fitting and adopt a fit only when it is better on '
               'held-out readings and covers no fewer directions.', {}),
    'refine_period': (DEFAULTS.refine_period,
                      'Seconds (of message stamps) between refinement fits; doubles up to 8x '
                      'once the calibration has converged.',
                      {'floating_point_range': _float_range(1.0, 3600.0)}),
    'online_tracking': (DEFAULTS.online_tracking,
                        'After a calibration, follow slow drift; a tracked calibration is adopted '
                        'only when clearly better, by bounded steps.', {}),
    'tracking_improvement': (DEFAULTS.tracking_improvement,
                             'Adopt a tracked calibration only when its residual is below this '
                             'share of the current one.',
                             {'floating_point_range': _float_range(0.05, 0.99)}),
    'tracking_max_change_rate': (DEFAULTS.tracking_max_change_rate,
                                 'Largest tracked change per second: offset as a share of the '
                                 'field, matrix as a relative norm.',
                                 {'floating_point_range': _float_range(1e-5, 0.5)}),
    'publish_uncalibrated': (False,
                             'Publish imu/mag_corrected as the raw field while no calibration '
                             'exists.', {}),
    'auto_save': (False, 'Save to calibration_file whenever a new calibration goes in force '
                         '(at most every 10 s; atomic).', {}),
    'calibration_file': ('',
                         'Calibration YAML (ROS params format): loaded at start-up and by ~/load, '
                         'written by ~/save. Default: one file per node, '
                         '$ROS_HOME/mag_calibrator/<namespace>__<name>.yaml.', {}),
    'progress_log_period': (5.0, 'Seconds between progress log lines while uncalibrated '
                                 '(0 = silent).',
                            {'floating_point_range': _float_range(0.0, 3600.0)}),
    'view_period': (1.0, 'Seconds between RViz views (~/view/raw, ~/view/corrected, '
                         '~/view/markers), drawn only while subscribed; 0 = never.',
                    {'floating_point_range': _float_range(0.0, 3600.0)}),
    'view_scale': (1e4, 'RViz view: metres per tesla (1e4: a 50 uT field is a 0.5 m sphere).',
                   {'floating_point_range': _float_range(1e-3, 1e9)}),
    # ~/rotate_and_calibrate (ground robots): turning in place on cmd_vel
    'rotation_speed': (ROTATION_DEFAULTS.speed,
                       'rad/s of the turn in place ~/rotate_and_calibrate commands on cmd_vel '
                       '(positive: counter-clockwise seen from above, a left turn).',
                       {'floating_point_range': _float_range(0.05, MAX_SPEED)}),
    'rotation_acceleration': (ROTATION_DEFAULTS.acceleration,
                              'rad/s^2 of the ramp from standstill to rotation_speed.',
                              {'floating_point_range': _float_range(0.05, 10.0)}),
    'rotation_timeout': (ROTATION_DEFAULTS.timeout_s,
                         'Seconds of turning after which ~/rotate_and_calibrate stops without a '
                         'calibration.', {'floating_point_range': _float_range(5.0, 3600.0)}),
    'cmd_vel_stamped': (False, "Publish geometry_msgs/TwistStamped on cmd_vel (as Jazzy's nav2 "
                               'and ros2_control use) instead of geometry_msgs/Twist.', {}),
    'cmd_vel_frame_id': ('base_link', 'header.frame_id of TwistStamped commands.', {}),
    'use_imu': (True, 'Subscribe imu/data_raw (sensor_msgs/Imu, same frame as imu/mag) and align '
                      'each calibration to the accelerometer from readings held still; without '
                      'a publisher nothing changes.', {}),
    'max_alignment_deg': (DEFAULTS.max_alignment_deg,
                          'A larger rotation to the IMU is reported as a mounting or axis-remap '
                          'error (with the remap that fixes it) and not applied.',
                          {'floating_point_range': _float_range(0.0, 180.0)}),
    'latitude': (math.nan, 'Degrees north (WGS84) for the World Magnetic Model; NaN: unknown '
                           '(the first fix on gps/fix is used).', {}),
    'longitude': (math.nan, 'Degrees east (WGS84) for the World Magnetic Model; NaN: unknown.',
                  {}),
    'altitude': (0.0, 'Metres above the WGS84 ellipsoid for the World Magnetic Model.',
                 {'floating_point_range': _float_range(-1000.0, 850000.0)}),
    'use_gps': (True, 'Without latitude/longitude, take the location from the first fix on '
                      'gps/fix (sensor_msgs/NavSatFix).', {}),
    'max_field_error_pct': (DEFAULTS.max_field_error_pct,
                            'Largest difference, in %, between the fitted field and the World '
                            "Magnetic Model's intensity before the field counts as disturbed.",
                            {'floating_point_range': _float_range(1.0, 100.0)}),
    'max_dip_error_deg': (DEFAULTS.max_dip_error_deg,
                          "Largest difference between the measured dip and the model's "
                          'inclination before the field counts as disturbed.',
                          {'floating_point_range': _float_range(0.1, 90.0)}),
    'earth_field_gate': (DEFAULTS.earth_field_gate,
                         'A fit off the World Magnetic Model beyond the tolerances fails (true) '
                         'or is only warned about (false).', {}),
}
SESSION_FIELDS = {f.name for f in fields(SessionSettings)}
CALIBRATION_METADATA_KEYS = (
    'residual_rms_pct', 'coverage', 'samples', 'time', 'frame_id', 'units', 'source',
    'plane_normal', 'unobserved', 'alignment_angle_deg', 'dip_deg', 'dip_std_deg',
    'static_samples', 'declination_deg',
)
"""Metadata a saved file may carry (declared so --params-file keeps it)."""
CALIBRATION_PARAMETERS: dict[str, str] = {
    'calibration.offset': 'Hard-iron offset b [3], tesla.',
    'calibration.matrix': 'Soft-iron matrix M [9], row-major.',
    'calibration.field_strength': '|corrected| target F, tesla (0.0 with model none).',
    'calibration.model': "Model of the calibration in force; 'none' while uncalibrated.",
    'calibration.rotation': 'Rotation R [9] into the IMU frame, row-major (identity: none).',
}
NO_CALIBRATION = {
    'calibration.offset': [0.0, 0.0, 0.0],
    'calibration.matrix': [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    'calibration.field_strength': 0.0,
    'calibration.model': 'none',
    'calibration.rotation': [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
}
"""What calibration.* hold while uncalibrated (a dump of it loads back as 'no calibration')."""
CALIBRATION_READ_ONLY = ('calibration.* show the calibration in force: change it with '
                         '~/calibrate, ~/load, or --params-file at start-up')


class MagCalibratorNode(Node):
    """Live magnetometer calibration; ``.session`` exposes the engine state (demo, tests)."""

    def __init__(self, **node_kwargs) -> None:
        node_kwargs.setdefault('node_name', NODE_NAME)
        super().__init__(**node_kwargs)
        self._default_file = default_calibration_path(self.get_fully_qualified_name())
        problems: list[str] = []
        for name, (default, description, extras) in PARAMETERS.items():
            if name == 'calibration_file':
                default = str(self._default_file)
            declare_checked(self, name, default,
                            ParameterDescriptor(description=description, **extras), problems)
        problems += self._problems(self._current_values())
        if problems:
            Node.destroy_node(self)  # nothing else was created yet
            refuse_to_start(self, problems)
        startup_calibration = self._declare_calibration_parameters()
        runner = ProcessRunner()
        runner.start()  # the worker imports the fitting stack while the node starts up
        self.session = CalibrationSession(self._settings_from(self._current_values()),
                                          runner=runner)
        self._io = ThreadPoolExecutor(max_workers=1, thread_name_prefix='mag_calibrator_io')
        self._io_results: SimpleQueue = SimpleQueue()  # (rclpy Future, result) from the I/O thread
        self._requests: dict[int, Future] = {}  # ~/calibrate tickets waiting for their answer
        self._problem: str | None = None  # a calibration file/parameter error, shown as ERROR
        self._last_progress_log = -math.inf
        self._save_wanted = False
        self._saving = False
        self._last_auto_save = -math.inf
        self._imu_subscription = None
        self._location_source = ''  # 'parameters' or 'gps/fix' once the model's field is known
        self._location_wanted: tuple[float, float, float] | None = None
        self._fix_used = False
        self._startup(startup_calibration)
        self._showing = False
        self.add_on_set_parameters_callback(self._validate_parameters)
        self._show_calibration()
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._publisher = self.create_publisher(
            MagneticField, 'imu/mag_corrected', QoSProfile(depth=10)
        )
        self.create_subscription(MagneticField, 'imu/mag', guarded(self, 'imu/mag', self._on_mag),
                                 INPUT_QOS)
        self._sync_imu_subscription()
        self.create_subscription(NavSatFix, 'gps/fix', guarded(self, 'gps/fix', self._on_fix),
                                 INPUT_QOS)
        self._locate_from_parameters()
        # The services wait for the fit worker and the I/O thread without blocking the executor;
        # a waiting service must not hold the default (mutually exclusive) group, or the poll
        # timer that completes it could never run.
        waiting = ReentrantCallbackGroup()
        for name, callback in (('~/calibrate', self._on_calibrate), ('~/save', self._on_save),
                               ('~/reset', self._on_reset), ('~/load', self._on_load)):
            self.create_service(Trigger, name, self._answering(name, callback),
                                callback_group=waiting)
        self._diagnostics = DiagnosticsPublisher(self)
        self._view = ViewPublisher(self)
        self._last_view = -math.inf
        self.create_timer(POLL_PERIOD_S, guarded(self, 'poll', self._on_poll))
        self.create_timer(DIAGNOSTICS_PERIOD_S, guarded(self, 'diagnostics', self._on_tick))
        self._start_rotation_wiring()

    def destroy_node(self) -> None:
        self._stop_rotation_for_shutdown()
        self.session.close()
        self._io.shutdown(wait=True)
        super().destroy_node()

    # -- parameters ------------------------------------------------------------------------------

    def _current_values(self) -> dict[str, object]:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    @staticmethod
    def _settings_from(values: dict[str, object]) -> SessionSettings:
        return SessionSettings(**{k: v for k, v in values.items() if k in SESSION_FIELDS})

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        if any(p.name.startswith('calibration.') for p in parameters) and not self._showing:
            return SetParametersResult(successful=False, reason=CALIBRATION_READ_ONLY)
        values = self._current_values()
        for parameter in parameters:
            if parameter.name in PARAMETERS:
                values[parameter.name] = parameter.value
        problems = self._problems(values)
        if problems:
            return SetParametersResult(successful=False, reason='; '.join(problems))
        return SetParametersResult(successful=True)

    def _problems(self, values: dict[str, object]) -> list[str]:
        """Everything wrong with these parameter values (the same at start-up and at run time)."""
        problems = self._settings_from(values).problems()
        problems += self._rotation_settings_from(values).problems()
        try:
            resolve_calibration_path(str(values['calibration_file']))
        except CalibrationFileError as error:
            problems.append(f'calibration_file: {error}')
        latitude, longitude = values['latitude'], values['longitude']
        if not (_is_nan(latitude) and _is_nan(longitude)):  # NaN and NaN: no location
            problems += location_problems(latitude, longitude, values['altitude'])
        return problems

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        if any(parameter.name in PARAMETERS for parameter in parameters):
            self.session.reconfigure(self._settings_from(self._current_values()))
        names = {parameter.name for parameter in parameters}
        if 'use_imu' in names:
            self._sync_imu_subscription()
        if names & {'latitude', 'longitude', 'altitude'}:
            self._locate_from_parameters()

    def _declare_calibration_parameters(self) -> dict[str, object]:
        """Declare ``calibration.*``: what --params-file gave (a saved file or a dump works as
        one) comes back; afterwards they always show the calibration in force.

        Dynamically typed, so a hand-written file with integers (``matrix: [1, 0, 0, ...]``) or
        a wrong type reaches calibration_from_parameters, which converts or says what is wrong,
        instead of rclpy refusing the whole node.
        """
        given = {}
        names = {**CALIBRATION_PARAMETERS,
                 **{f'calibration.{key}': f'Calibration metadata ({key}); informational.'
                    for key in CALIBRATION_METADATA_KEYS}}
        for name, description in names.items():
            descriptor = ParameterDescriptor(description=description, dynamic_typing=True)
            value = self.declare_parameter(name, None, descriptor).value
            if value is not None:
                given[name] = value
        if given.get('calibration.model') == NO_CALIBRATION['calibration.model']:
            return {}  # a dump of an uncalibrated node: no calibration given
        return given

    def _show_calibration(self) -> None:
        """Set ``calibration.*`` to the calibration in force (``ros2 param get/dump`` read it),
        metadata it does not carry left unset, never NOT_SET: a dump loads back as given."""
        calibration = self.session.calibration
        self._shown_calibration = calibration
        values = dict(NO_CALIBRATION)
        if calibration is not None:
            try:
                values = calibration_parameters(calibration)
            except CalibrationFileError as error:
                self.get_logger().warning(f'calibration.* not updated: {error}')
                return
        parameters = []
        for name, value in values.items():
            try:
                parameters.append(Parameter(name, value=value))
            except TypeError:  # metadata no parameter can hold (a mixed list ...)
                continue
        kept = {parameter.name for parameter in parameters}
        self._showing = True  # our own change: _validate_parameters lets it through
        try:
            for key in CALIBRATION_METADATA_KEYS:
                name = f'calibration.{key}'
                if name not in kept and self.has_parameter(name):
                    self.undeclare_parameter(name)
            for parameter in parameters:
                if not self.has_parameter(parameter.name):
                    self.declare_parameter(parameter.name, None, ParameterDescriptor(
                        description='Calibration metadata; informational.',
                        dynamic_typing=True))
            self.set_parameters(parameters)
        finally:
            self._showing = False

    # -- start-up --------------------------------------------------------------------------------

    def _calibration_file(self) -> Path:
        return resolve_calibration_path(str(self.get_parameter('calibration_file').value))

    def _startup(self, parameters: dict[str, object]) -> None:
        """Parameters given with --params-file win; else the file; else run uncalibrated."""
        if any(name in parameters for name in CALIBRATION_PARAMETERS):
            try:
                calibration = self._calibration_from(parameters)
            except (CalibrationError, ValueError, TypeError) as error:
                self._report_problem(f'calibration.* parameters unusable: {error}')
            else:
                self.session.apply_calibration(calibration, 'parameters')
                self.get_logger().info(
                    f'calibration from parameters: {calibration_summary(calibration)}')
            return
        path = self._calibration_file()
        if path == resolve_calibration_path(self._default_file):  # the per-node default,
            path = default_load_path(self.get_fully_qualified_name())  # or the old shared file
        loaded = _read_calibration(path, self.get_fully_qualified_name())
        if loaded is None:
            self.get_logger().info(
                f'no calibration file at {path} yet: uncalibrated until ~/calibrate '
                f'(auto_calibrate={self.get_parameter("auto_calibrate").value})'
            )
            return
        self._loaded(path, loaded)

    @staticmethod
    def _calibration_from(parameters: dict[str, object]) -> Calibration:
        metadata = {
            name.removeprefix('calibration.'): value
            for name, value in parameters.items()
            if name not in CALIBRATION_PARAMETERS
        }
        return calibration_from_parameters(
            offset=parameters.get('calibration.offset'),
            matrix=parameters.get('calibration.matrix'),
            field_strength=parameters.get('calibration.field_strength'),
            model=parameters.get('calibration.model', 'full'),
            metadata=metadata,
            rotation=parameters.get('calibration.rotation'),
        )

    def _loaded(self, path: Path, loaded: LoadedCalibration | Exception) -> tuple[bool, str]:
        """Put a calibration read from ``path`` in force, or report why it could not be."""
        if isinstance(loaded, Exception):
            return False, self._report_problem(
                f'{loaded}; the calibration in force is unchanged (state {self.session.state})')
        for note in loaded.notes:
            self.get_logger().warning(f'{loaded.path}: {note}')
        self.session.apply_calibration(loaded.calibration, 'file')
        self._problem = None
        message = f'loaded {loaded.path}: {calibration_summary(loaded.calibration)}'
        self.get_logger().info(message)
        return True, message

    def _report_problem(self, message: str) -> str:
        self._problem = message
        self.get_logger().error(message)
        return message

    # -- stream ----------------------------------------------------------------------------------

    def _on_mag(self, msg: MagneticField) -> None:
        field = msg.magnetic_field
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        frame = msg.header.frame_id
        processed = self.session.process(stamp_ns, frame, (field.x, field.y, field.z))
        if processed.corrected is not None:
            out = MagneticField(header=msg.header)
            out.magnetic_field.x, out.magnetic_field.y, out.magnetic_field.z = (
                processed.corrected.tolist())
            out.magnetic_field_covariance = transform_covariance(
                processed.calibration.correction, msg.magnetic_field_covariance
            )
            self._publisher.publish(out)
        elif processed.accepted and self.get_parameter('publish_uncalibrated').value:
            self._publisher.publish(msg)
        if self.session.has_events:
            self._handle_events()

    def _on_imu(self, msg: Imu) -> None:
        """O(1): the session keeps the sample to pair magnetometer readings with."""
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        accel, rate = msg.linear_acceleration, msg.angular_velocity
        gyro = None if msg.angular_velocity_covariance[0] == -1.0 else (rate.x, rate.y, rate.z)
        self.session.process_imu(stamp_ns, msg.header.frame_id, (accel.x, accel.y, accel.z),
                                 gyro)

    def _sync_imu_subscription(self) -> None:
        wanted = bool(self.get_parameter('use_imu').value)
        if wanted and self._imu_subscription is None:
            self._imu_subscription = self.create_subscription(
                Imu, 'imu/data_raw', guarded(self, 'imu/data_raw', self._on_imu), INPUT_QOS)
        elif not wanted and self._imu_subscription is not None:
            self.destroy_subscription(self._imu_subscription)
            self._imu_subscription = None

    # -- the Earth's field here -------------------------------------------------------------------

    def _locate_from_parameters(self) -> None:
        latitude = float(self.get_parameter('latitude').value)
        longitude = float(self.get_parameter('longitude').value)
        if math.isnan(latitude) and math.isnan(longitude):
            if self._location_source == 'parameters':
                self._location_source = ''
                self.session.set_earth_field(None)
            return
        self._locate(latitude, longitude, float(self.get_parameter('altitude').value),
                     'parameters')

    def _on_fix(self, msg: NavSatFix) -> None:
        """The first usable fix locates the robot when the parameters do not (one evaluation
        only, whatever its outcome: a fix stream never repeats it)."""
        if (self._fix_used or not self.get_parameter('use_gps').value
                or msg.status.status < NavSatStatus.STATUS_FIX
                or not (_is_nan(self.get_parameter('latitude').value)
                        and _is_nan(self.get_parameter('longitude').value))):
            return
        altitude = msg.altitude if math.isfinite(msg.altitude) else 0.0
        if location_problems(msg.latitude, msg.longitude, altitude):
            return
        self._fix_used = True
        self._locate(msg.latitude, msg.longitude, altitude, 'gps/fix')

    def _locate(self, latitude: float, longitude: float, altitude: float, source: str) -> None:
        """Evaluate the World Magnetic Model on the I/O thread (an import and ~30 ms)."""
        where = (latitude, longitude, altitude)
        self._location_wanted = where
        self._run_io(lambda: earth_field(*where)).add_done_callback(
            lambda future: self._located(where, source, future.result()))

    def _located(self, where: tuple[float, float, float], source: str,
                 result: EarthField | Exception) -> None:
        if where != self._location_wanted:
            return  # a newer location was asked for meanwhile
        self._location_wanted = None
        if isinstance(result, Exception):
            what = '' if isinstance(result, EarthFieldError) else f'{type(result).__name__}: '
            self.get_logger().warning(f'no World Magnetic Model field at {where} (from '
                                      f'{source}): {what}{result}; running without it')
            return
        self._location_source = source
        self.session.set_earth_field(result)
        self.get_logger().info(f'earth field here (from {source}): {result.describe()}')
        for note in result.notes:
            self.get_logger().warning(note)

    # -- what the session decided -----------------------------------------------------------------

    def _on_poll(self) -> None:
        """Collect finished fits and file operations; answer waiting services; auto-save;
        show a new calibration in force as calibration.* parameters."""
        self.session.poll()
        while not self._io_results.empty():
            future, result = self._io_results.get()
            future.set_result(result)
        if self.session.has_events:
            self._handle_events()
        if self.session.calibration is not self._shown_calibration:
            self._show_calibration()
        if self._save_wanted and not self._saving and (
                time.monotonic() - self._last_auto_save >= AUTO_SAVE_MIN_INTERVAL_S):
            self._save_wanted = False
            self._last_auto_save = time.monotonic()
            self._saving = True
            self._run_io(self._save_file).add_done_callback(
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
                self._save_wanted = bool(self.get_parameter('auto_save').value)
            request = self._requests.pop(event.ticket, None)
            if request is not None:
                request.set_result(event.attempt)

    def _run_io(self, work: Callable[[], object]) -> Future:
        """Run ``work`` on the I/O thread; the Future completes on the executor thread (from the
        poll timer) with its result, or with the exception it raised."""
        future = Future()

        def run() -> None:
            try:
                result = work()
            except Exception as error:  # noqa: BLE001 - reported, never raised into the executor
                result = error
            self._io_results.put((future, result))

        self._io.submit(run)
        return future

    # -- services --------------------------------------------------------------------------------

    def _answering(self, name: str, callback: Callable) -> Callable:
        """A service callback that always answers: an unexpected error fails the call with its
        text (and the traceback in the log) instead of leaving the client waiting forever."""

        async def answer(request: Trigger.Request, response: Trigger.Response):
            try:
                result = callback(request, response)
                return await result if inspect.isawaitable(result) else result
            except Exception as error:  # noqa: BLE001 - reported to the caller and the log
                self.get_logger().error(f'{name} failed:\n{traceback.format_exc()}')
                response.success = False
                response.message = f'{name} failed: {type(error).__name__}: {error}'
                return response

        return answer

    async def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response):
        waiting = Future()
        self._requests[self.session.request_calibration()] = waiting
        self._handle_events()  # an immediate answer (nothing to wait for)
        attempt = await waiting
        response.success, response.message = attempt.success, attempt.message
        return response

    def _save_file(self) -> str:
        """On the I/O thread: write the calibration in force (it is immutable)."""
        calibration = self.session.calibration
        if calibration is None:
            raise ValueError('nothing to save: no calibration in force (call ~/calibrate first)')
        written = save_calibration(self._calibration_file(), calibration,
                                   node_name=self.get_fully_qualified_name())
        return f'saved to {written}'

    def _auto_saved(self, result: object) -> None:
        self._saving = False
        if isinstance(result, Exception):
            self.get_logger().warning(f'auto_save failed: {result}')
        else:
            self.get_logger().info(f'auto_save: {result}')

    async def _on_save(self, request: Trigger.Request, response: Trigger.Response):
        result = await self._run_io(self._save_file)
        response.success = not isinstance(result, Exception)
        response.message = str(result)
        if response.success:  # one call site per severity (rclpy refuses a change at one)
            self.get_logger().info(response.message)
        else:
            self.get_logger().warning(f'save failed: {result}')
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        self.session.reset()
        response.success = True
        response.message = (f'buffer emptied; the calibration in force is unchanged '
                            f'(state {self.session.state})')
        self.get_logger().info(response.message)
        return response

    async def _on_load(self, request: Trigger.Request, response: Trigger.Response):
        path = self._calibration_file()
        name = self.get_fully_qualified_name()
        loaded = await self._run_io(lambda: _read_calibration(path, name))
        if loaded is None:
            response.success = False
            response.message = f'no calibration file at {path}; the calibration in force stays'
        else:
            response.success, response.message = self._loaded(path, loaded)
        return response

    # -- once per second -------------------------------------------------------------------------

    def _on_tick(self) -> None:
        now = time.monotonic()
        coverage = self.session.reported_coverage()
        self._log_progress(now, coverage)
        self._publish_diagnostics(now, coverage)
        self._publish_view(now)

    def _publish_view(self, now: float) -> None:
        period = float(self.get_parameter('view_period').value)
        if period <= 0.0 or now - self._last_view < period or not self._view.watched:
            return
        self._last_view = now
        self._view.publish(self.session.view(), self.session.frame_id or 'imu_link',
                           float(self.get_parameter('view_scale').value))

    def _log_progress(self, now: float, coverage: Coverage) -> None:
        period = float(self.get_parameter('progress_log_period').value)
        if period <= 0.0 or self.session.calibration is not None:
            return
        if self._rotation.state == 'turning':
            return  # the rotation logs its own progress
        if now - self._last_progress_log >= period:
            self._last_progress_log = now
            if self.session.input_rate_hz == 0.0:
                self.get_logger().info(self._no_input_text())
            else:
                self.get_logger().info(self.session.progress_text(coverage))

    def _no_input_text(self) -> str:
        topic = self.resolve_topic_name('imu/mag')
        return (f'no input on {topic}: is the driver running, in this namespace? '
                f'(ros2 topic info {topic})')

    def _publish_diagnostics(self, now: float, coverage: Coverage) -> None:
        values = self.session.diagnostic_values(now, coverage)
        values['calibration_file'] = str(self._calibration_file())
        values.update(self._rotation.diagnostic_values(now))
        if self._location_source:
            values['location_source'] = self._location_source
        level, message = self.session.diagnostics_level(
            coverage, values['input_rate_hz'], self._problem, self._no_input_text())
        # Names and hardware ids carry the namespace: robots on one host stay apart.
        topic = self.resolve_topic_name('imu/mag')
        frame = self.session.frame_id
        hardware_id = f'{topic} ({frame})' if frame else topic
        self._diagnostics.publish([
            diagnostic_status(f'{self.get_fully_qualified_name()}: calibration', hardware_id,
                              {'OK': OK, 'WARN': WARN, 'ERROR': ERROR}[level], message, values)
        ])

    # -- turning in place: ~/rotate_and_calibrate, ~/stop_rotation -------------------------------
    # Every decision is the RotationController's; this wires it: a 20 Hz timer publishes what it
    # commands, every stop path publishes zero at once, and the publisher on cmd_vel exists only
    # while a rotation runs (and for its zero hold).

    @staticmethod
    def _rotation_settings_from(values: dict[str, object]) -> RotationSettings:
        return RotationSettings(speed=float(values['rotation_speed']),
                                acceleration=float(values['rotation_acceleration']),
                                timeout_s=float(values['rotation_timeout']))

    def _start_rotation_wiring(self) -> None:
        self._rotation = RotationController(
            self._rotation_settings_from(self._current_values()),
            input_topic=self.resolve_topic_name('imu/mag'),
            command_topic=self.resolve_topic_name(COMMAND_TOPIC))
        self._command_publisher = None
        self._command_stamped = False
        self._accepted_seen = self.session.accepted
        self._last_input: float | None = None  # monotonic time the accepted count last grew
        for name, callback in (('~/rotate_and_calibrate', self._on_rotate),
                               ('~/stop_rotation', self._on_stop_rotation)):
            self.create_service(Trigger, name, self._answering(name, callback))
        self.add_post_set_parameters_callback(self._rotation_parameters_changed)
        self.create_timer(COMMAND_PERIOD_S, guarded(self, 'rotation', self._on_rotation_timer))

    def _input_age(self, now: float) -> float | None:
        """Seconds since a reading was last accepted (sampled every COMMAND_PERIOD_S)."""
        if self.session.accepted != self._accepted_seen:
            self._accepted_seen = self.session.accepted
            self._last_input = now
        return None if self._last_input is None else now - self._last_input

    def _other_commanders(self) -> int:
        publishers = self.count_publishers(self.resolve_topic_name(COMMAND_TOPIC))
        return publishers - (self._command_publisher is not None)

    def _on_rotation_timer(self) -> None:
        try:
            self._rotation_tick()
        except Exception:
            self._stop_rotation('error')  # never keep turning on an error; guarded logs it
            raise

    def _rotation_tick(self) -> None:
        now = time.monotonic()
        input_age = self._input_age(now)
        if self._rotation.state == 'idle' and self._command_publisher is None:
            return
        step = self._rotation.update(now, input_age, self._other_commanders(),
                                     lambda: self.session.heading_coverage().coverage)
        self._rotation_log(step.messages)
        if step.calibrate:
            self._request_rotation_fit()  # its answer may already have stopped the rotation
        self._publish_command(self._rotation.command(now))

    def _publish_command(self, yaw_rate: float | None) -> None:
        """Publish a turn command (None: nothing; the publisher goes once a stop's zeros are
        sent)."""
        if yaw_rate is None:
            if self._command_publisher is not None:
                self.destroy_publisher(self._command_publisher)
                self._command_publisher = None
            return
        if self._command_publisher is None:
            self._command_stamped = bool(self.get_parameter('cmd_vel_stamped').value)
            self._command_publisher = self.create_publisher(
                TwistStamped if self._command_stamped else Twist, COMMAND_TOPIC, COMMAND_QOS)
        twist = Twist()
        twist.angular.z = float(yaw_rate)
        if self._command_stamped:
            message = TwistStamped(twist=twist)
            message.header.stamp = self.get_clock().now().to_msg()
            message.header.frame_id = str(self.get_parameter('cmd_vel_frame_id').value)
        else:
            message = twist
        self._command_publisher.publish(message)

    def _rotation_log(self, messages) -> None:
        for message in messages:
            if message:
                self.get_logger().info(message)

    def _stop_rotation(self, reason: str, detail: str = '') -> str | None:
        """Stop for ``reason`` and publish the zero at once (not at the next tick)."""
        now = time.monotonic()
        line = self._rotation.stop(now, reason, detail)
        if line is not None:
            self._rotation_log([line])
            self._publish_command(self._rotation.command(now))
        return line

    def _on_rotate(self, request: Trigger.Request, response: Trigger.Response):
        now = time.monotonic()
        started, message = self._rotation.start(now, self._input_age(now),
                                                self._other_commanders())
        if started:
            self.session.reset()  # a rotation calibrates from what it sees, not older samples
            self._publish_command(self._rotation.command(now))
            self.get_logger().info(message)
        else:
            self.get_logger().warning(f'~/rotate_and_calibrate refused: {message}')
        response.success, response.message = started, message
        return response

    def _on_stop_rotation(self, request: Trigger.Request, response: Trigger.Response):
        line = self._stop_rotation('requested')
        response.success = True
        response.message = line or f'not rotating ({self._rotation.progress_text(0.0)})'
        return response

    def _request_rotation_fit(self) -> None:
        waiting = Future()
        waiting.add_done_callback(self._rotation_fit_done)
        self._requests[self.session.request_calibration()] = waiting
        self._handle_events()  # an immediate answer

    def _rotation_fit_done(self, future: Future) -> None:
        attempt = future.result()
        error = attempt.outcome is not None and bool(attempt.outcome.error)
        now = time.monotonic()
        line = self._rotation.calibration_answered(now, attempt.success, error, attempt.message)
        if line is not None:
            self._rotation_log([line])
            self._publish_command(self._rotation.command(now))

    def _rotation_parameters_changed(self, parameters: list[Parameter]) -> None:
        self._rotation.settings = self._rotation_settings_from(self._current_values())
        changed = [p.name for p in parameters if not p.name.startswith('calibration.')]
        if changed:
            self._stop_rotation('parameters', ', '.join(changed))

    def _stop_rotation_for_shutdown(self) -> None:
        """Zero on the way out, acknowledged by the subscribers if they can (bounded)."""
        try:
            self._stop_rotation('shutdown')
            publisher = self._command_publisher
            if publisher is not None:
                self._publish_command(0.0)
                publisher.wait_for_all_acked(Duration(nanoseconds=int(SHUTDOWN_ACK_S * 1e9)))
                self.destroy_publisher(publisher)
                self._command_publisher = None
        except Exception as error:  # noqa: BLE001 - shutting down: report, never raise
            self.get_logger().error(f'could not command zero on shutdown: {error!r}')


def _is_nan(value: object) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _read_calibration(path: Path, node_name: str) -> LoadedCalibration | Exception | None:
    """Read a calibration file for ``node_name``: None when there is none, any failure as the
    exception (reported, never raised)."""
    try:
        return read_calibration_file(path, node_name)
    except CalibrationFileMissingError:
        return None
    except (CalibrationFileError, CalibrationError) as error:
        return error


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``mag_calibrator`` (also ``ros2 run mag_calibrator_ros mag_calibrator``):
    exit 0 on a normal stop, 2 on invalid parameters."""
    try:  # on Ctrl-C/SIGTERM the node still publishes a final zero on cmd_vel
        return spin_node(MagCalibratorNode, args, publish_on_shutdown=True)
    except ConfigurationError:
        return 2  # already logged as FATAL with every problem


if __name__ == '__main__':
    raise SystemExit(main())

