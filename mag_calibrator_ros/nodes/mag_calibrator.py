"""``mag_calibrator`` node: raw ``imu/mag`` in, ``imu/mag_corrected`` out, services to calibrate.

Wiring only: parameters, the subscription, the publisher, four std_srvs/Trigger services and the
diagnostics timer. Every decision (screening, buffer, fits, auto-calibration, online tracking,
progress text) lives in :class:`~mag_calibrator_ros.calibration.session.CalibrationSession`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
import math
from pathlib import Path
import time

import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.calibration_file import (
    CalibrationFileError,
    calibration_from_parameters,
)
from mag_calibrator_ros.calibration.session import (
    FITTABLE_MODELS,
    CalibrationSession,
    SessionSettings,
    transform_covariance,
)
from mag_calibrator_ros.nodes.diagnostics import (
    ERROR,
    OK,
    WARN,
    DiagnosticsPublisher,
    diagnostic_status,
)
from mag_calibrator_ros.nodes.runtime import spin_node

NODE_NAME = 'mag_calibrator'
DEFAULT_CALIBRATION_FILE = '~/.ros/mag_calibrator/calibration.yaml'
DIAGNOSTICS_PERIOD_S = 1.0
INPUT_QOS = QoSProfile(
    history=qos_profile_sensor_data.history,
    depth=100,  # sensor-data QoS (best effort, REP-2003) with room for bursts at 1 kHz
    reliability=qos_profile_sensor_data.reliability,
    durability=qos_profile_sensor_data.durability,
)
DEFAULTS = SessionSettings()


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
                       'While uncalibrated, calibrate by itself once coverage and fit pass the '
                       'gates.', {}),
    'auto_calibrate_period': (DEFAULTS.auto_calibrate_period,
                              'Seconds between automatic calibration attempts.',
                              {'floating_point_range': _float_range(0.5, 3600.0)}),
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
    'auto_save': (False, 'Save to calibration_file after every successful calibration.', {}),
    'calibration_file': (DEFAULT_CALIBRATION_FILE,
                         'Calibration YAML (ROS params format): loaded at start-up and by ~/load, '
                         'written by ~/save.', {}),
    'progress_log_period': (5.0, 'Seconds between progress log lines while uncalibrated '
                                 '(0 = silent).',
                            {'floating_point_range': _float_range(0.0, 3600.0)}),
}
SESSION_FIELDS = {f.name for f in fields(SessionSettings)}
CALIBRATION_METADATA_KEYS = (
    'residual_rms_pct', 'coverage', 'samples', 'time', 'frame_id', 'units', 'source',
    'plane_normal', 'unobserved',
)
"""Metadata the fit and the node write into a saved file (declared so --params-file keeps it)."""
CALIBRATION_PARAMETERS: dict[str, tuple[Parameter.Type, str]] = {
    'calibration.offset': (Parameter.Type.DOUBLE_ARRAY, 'Hard-iron offset b [3], tesla.'),
    'calibration.matrix': (Parameter.Type.DOUBLE_ARRAY, 'Soft-iron matrix M [9], row-major.'),
    'calibration.field_strength': (Parameter.Type.DOUBLE, '|corrected| target F, tesla.'),
    'calibration.model': (Parameter.Type.STRING, 'Model that produced the calibration.'),
}


class MagCalibratorNode(Node):
    """Live magnetometer calibration; ``.session`` exposes the engine state (demo, tests)."""

    def __init__(self, **node_kwargs) -> None:
        node_kwargs.setdefault('node_name', NODE_NAME)
        super().__init__(**node_kwargs)
        for name, (default, description, extras) in PARAMETERS.items():
            self.declare_parameter(
                name, default, ParameterDescriptor(description=description, **extras)
            )
        startup_calibration = self._declare_calibration_parameters()
        self.session = CalibrationSession(self._settings_from(self._current_values()))
        self._problem: str | None = None  # a calibration file/parameter error, shown as ERROR
        self._last_progress_log = -math.inf
        self._startup(startup_calibration)

        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._publisher = self.create_publisher(
            MagneticField, 'imu/mag_corrected', QoSProfile(depth=10)
        )
        self.create_subscription(MagneticField, 'imu/mag', self._on_mag, INPUT_QOS)
        self.create_service(Trigger, '~/calibrate', self._on_calibrate)
        self.create_service(Trigger, '~/save', self._on_save)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/load', self._on_load)
        self._diagnostics = DiagnosticsPublisher(self)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._on_tick)

    # -- parameters ------------------------------------------------------------------------------

    def _current_values(self) -> dict[str, object]:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    @staticmethod
    def _settings_from(values: dict[str, object]) -> SessionSettings:
        return SessionSettings(**{k: v for k, v in values.items() if k in SESSION_FIELDS})

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        values = self._current_values()
        for parameter in parameters:
            if parameter.name in PARAMETERS:
                values[parameter.name] = parameter.value
        problems = self._settings_from(values).problems()
        if not str(values['calibration_file']).strip():
            problems.append('calibration_file must not be empty')
        if problems:
            return SetParametersResult(successful=False, reason='; '.join(problems))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        self.session.reconfigure(self._settings_from(self._current_values()))

    def _declare_calibration_parameters(self) -> dict[str, object]:
        """Declare ``calibration.*`` (read-only, start-up): a saved file works as --params-file."""
        given = {}
        for name, (kind, description) in CALIBRATION_PARAMETERS.items():
            value = self.declare_parameter(
                name, kind, ParameterDescriptor(description=description, read_only=True)
            ).value
            if value is not None:
                given[name] = value
        for key in CALIBRATION_METADATA_KEYS:
            name = f'calibration.{key}'
            if self.has_parameter(name):
                continue
            descriptor = ParameterDescriptor(
                description=f'Calibration metadata ({key}); informational.',
                read_only=True,
                dynamic_typing=True,
            )
            value = self.declare_parameter(name, None, descriptor).value
            if value is not None:
                given[name] = value
        return given

    # -- start-up --------------------------------------------------------------------------------

    def _calibration_file(self) -> Path:
        return Path(str(self.get_parameter('calibration_file').value)).expanduser()

    def _startup(self, parameters: dict[str, object]) -> None:
        """Parameters given with --params-file win; else the file; else run uncalibrated."""
        if any(name in parameters for name in CALIBRATION_PARAMETERS):
            try:
                calibration = self._calibration_from(parameters)
            except (CalibrationError, ValueError, TypeError) as error:
                self._report_problem(f'calibration.* parameters unusable: {error}')
            else:
                self.session.apply_calibration(calibration)
                self.get_logger().info(
                    f'calibration from parameters: model {calibration.model}, offset '
                    f'{np.round(calibration.offset * 1e6, 2).tolist()} uT'
                )
            return
        path = self._calibration_file()
        if not path.exists():
            self.get_logger().info(
                f'no calibration file at {path} yet: uncalibrated until ~/calibrate '
                f'(auto_calibrate={self.get_parameter("auto_calibrate").value})'
            )
            return
        self._load_file()

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
        )

    def _load_file(self) -> tuple[bool, str]:
        try:
            message = self.session.load(self._calibration_file())
        except (CalibrationFileError, CalibrationError, OSError) as error:
            return False, self._report_problem(
                f'{error}; the calibration in force is unchanged (state {self.session.state})')
        self._problem = None
        self.get_logger().info(message)
        return True, message

    def _report_problem(self, message: str) -> str:
        self._problem = message
        self.get_logger().error(message)
        return message

    # -- stream ----------------------------------------------------------------------------------

    def _on_mag(self, msg: MagneticField) -> None:
        field = np.array([msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z])
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if self.session.ingest(stamp_ns, msg.header.frame_id, field) is not None:
            return
        corrected = self.session.correct(field)
        if corrected is None:
            if self.get_parameter('publish_uncalibrated').value:
                self._publisher.publish(msg)
            return
        out = MagneticField(header=msg.header)
        out.magnetic_field.x, out.magnetic_field.y, out.magnetic_field.z = corrected.tolist()
        out.magnetic_field_covariance = transform_covariance(
            self.session.calibration.matrix, msg.magnetic_field_covariance
        )
        self._publisher.publish(out)

    # -- services --------------------------------------------------------------------------------

    def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response):
        attempt = self.session.calibrate()
        response.success, response.message = attempt.success, attempt.message
        if attempt.success:
            self._problem = None
            self.get_logger().info(f'calibrated: {attempt.message}')
            response.message += self._auto_save()
        else:
            self.get_logger().warning(attempt.message)
        return response

    def _auto_save(self) -> str:
        if not self.get_parameter('auto_save').value:
            return ''
        success, message = self._save()
        return f'; {message}' if success else f'; auto_save failed: {message}'

    def _save(self) -> tuple[bool, str]:
        try:
            message = self.session.save(self._calibration_file())
        except (ValueError, OSError) as error:
            self.get_logger().warning(f'save failed: {error}')
            return False, str(error)
        self.get_logger().info(message)
        return True, message

    def _on_save(self, request: Trigger.Request, response: Trigger.Response):
        response.success, response.message = self._save()
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        self.session.reset()
        response.success = True
        response.message = (f'buffer emptied; the calibration in force is unchanged '
                            f'(state {self.session.state})')
        self.get_logger().info(response.message)
        return response

    def _on_load(self, request: Trigger.Request, response: Trigger.Response):
        path = self._calibration_file()
        if not path.exists():
            response.success = False
            response.message = f'no calibration file at {path}; the calibration in force stays'
            return response
        response.success, response.message = self._load_file()
        return response

    # -- once per second -------------------------------------------------------------------------

    def _on_tick(self) -> None:
        now = time.monotonic()
        attempt = self.session.maybe_auto_calibrate(now)
        if attempt is not None:
            if attempt.success:
                self._problem = None
                self.get_logger().info(f'calibrated automatically: {attempt.message}'
                                       f'{self._auto_save()}')
            else:
                self.get_logger().info(f'automatic calibration not yet: {attempt.message}')
        if self.session.maybe_adopt_tracked(now):
            self.get_logger().debug('adopted a step of the online-tracked calibration')
        self._log_progress(now)
        self._publish_diagnostics(now)

    def _log_progress(self, now: float) -> None:
        period = float(self.get_parameter('progress_log_period').value)
        if period <= 0.0 or self.session.calibration is not None:
            return
        if now - self._last_progress_log >= period:
            self._last_progress_log = now
            self.get_logger().info(self.session.progress_text())

    def _publish_diagnostics(self, now: float) -> None:
        values = self.session.diagnostic_values(now)
        values['calibration_file'] = str(self._calibration_file())
        state = self.session.state
        if self._problem is not None:
            level, message = ERROR, self._problem
        elif refused := self.session.new_screen_rejects():
            counts = ', '.join(f'{reason} {count}' for reason, count in refused.items())
            level, message = WARN, f'{state}: input messages refused since last report: {counts}'
        elif state == 'calibrated':
            level, message = OK, self.session.progress_text()
        elif values['input_rate_hz'] == 0.0:
            level, message = WARN, f'{state}: no input on {self.resolve_topic_name("imu/mag")}'
        else:
            level, message = WARN, f'{state}: {self.session.progress_text()}'
        hardware_id = self.session.frame_id or self.get_fully_qualified_name()
        self._diagnostics.publish([
            diagnostic_status(f'{self.get_name()}: calibration', hardware_id, level, message,
                              values)
        ])


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``mag_calibrator`` (also ``ros2 run mag_calibrator_ros mag_calibrator``)."""
    return spin_node(MagCalibratorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())

