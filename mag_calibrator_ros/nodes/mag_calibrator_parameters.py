# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The ``mag_calibrator`` node's parameters: the descriptor table and the checks of its values.

One table, so ``ros2 param describe``, the shipped config and the checks cannot disagree: every
entry is (default, description, descriptor extras such as ranges). Session settings share their
field names with :class:`~mag_calibrator_ros.calibration.live.session.SessionSettings`.
``parameter_problems`` is the one check, the same at start-up and on every later set, but for
one case: half a location (``latitude`` or ``longitude`` alone) is refused at start-up, where
nothing else can complete it, and waits for the other at run time (``ros2 param set`` sets one at
a time; see ``nodes/location.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
import math

from rcl_interfaces.msg import FloatingPointRange, IntegerRange

from mag_calibrator_ros.calibration.live.compensation import MAX_WINDOW_S
from mag_calibrator_ros.calibration.live.settings import FITTABLE_MODELS, SessionSettings
from mag_calibrator_ros.calibration.live.turning import MAX_SPEED, TurnSettings
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    resolve_calibration_path,
)
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.nodes.inputs import input_topic_problems
from mag_calibrator_ros.nodes.location import parameter_location_problems
from mag_calibrator_ros.nodes.turning import turn_settings_from

DEFAULTS = SessionSettings()
TURN_DEFAULTS = TurnSettings()

AK09916_FULL_SCALE_T = reg.MEASUREMENT_LIMIT * reg.TESLA_PER_LSB
"""The AK09916 saturates at its measurement limit (ST2 HOFL beyond it), in tesla: the
``full_scale`` default (the engine's own is 0, no check: it knows no chip)."""


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
    'full_scale': (AK09916_FULL_SCALE_T,
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
    'rotation_speed': (TURN_DEFAULTS.speed,
                       'rad/s of the turn in place ~/rotate_and_calibrate commands on cmd_vel '
                       '(positive: counter-clockwise seen from above, a left turn).',
                       {'floating_point_range': _float_range(0.05, MAX_SPEED)}),
    'rotation_acceleration': (TURN_DEFAULTS.acceleration,
                              'rad/s^2 of the ramp from standstill to rotation_speed.',
                              {'floating_point_range': _float_range(0.05, 10.0)}),
    'rotation_timeout': (TURN_DEFAULTS.timeout_s,
                         'Seconds of turning after which ~/rotate_and_calibrate stops without a '
                         'calibration.', {'floating_point_range': _float_range(5.0, 3600.0)}),
    'cmd_vel_stamped': (False, "Publish geometry_msgs/TwistStamped on cmd_vel (as Jazzy's nav2 "
                               'and ros2_control use) instead of geometry_msgs/Twist.', {}),
    'cmd_vel_frame_id': ('base_link', 'header.frame_id of TwistStamped commands.', {}),
    'use_imu': (True, 'Subscribe imu/data_raw (sensor_msgs/Imu, same frame as imu/mag) and align '
                      'each calibration to the accelerometer from readings held still; without '
                      'a publisher nothing changes.', {}),
    'gyro_aided': (DEFAULTS.gyro_aided,
                   "With imu/data_raw's gyroscope, calibrate first from the turning it measures "
                   '(the offset from rotation about two axes, no sphere needed), in force only '
                   'when better than the raw field on held-out readings; refinements must not '
                   'turn directions worse.', {}),
    'max_alignment_deg': (DEFAULTS.max_alignment_deg,
                          'A larger rotation to the IMU is reported as a mounting or axis-remap '
                          'error (with the remap that fixes it) and not applied.',
                          {'floating_point_range': _float_range(0.0, 180.0)}),
    'latitude': (math.nan, 'Degrees north (WGS84) for the World Magnetic Model; NaN: unknown '
                           '(a plausible fix on gps/fix is used). Set one at a time, the pair '
                           'goes in force once both are given (or both NaN).', {}),
    'longitude': (math.nan, 'Degrees east (WGS84) for the World Magnetic Model; NaN: unknown.',
                  {}),
    'altitude': (0.0, 'Metres above the WGS84 ellipsoid for the World Magnetic Model.',
                 {'floating_point_range': _float_range(-1000.0, 850000.0)}),
    'use_gps': (True, 'Without latitude/longitude, take the location from a plausible fix on '
                      'gps/fix (sensor_msgs/NavSatFix); a fix over 10 km away replaces it.', {}),
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
    # the robot's own field: corrected = R M (raw - b - K u - c (T - T0))
    'use_temperature': (DEFAULTS.use_temperature,
                        'Subscribe imu/temperature (sensor_msgs/Temperature) and learn and '
                        "compensate the hard iron's drift with the sensor's temperature; "
                        'without a publisher nothing changes.', {}),
    'interference_inputs': (list(DEFAULTS.interference_inputs),
                            'Inputs whose field the robot carries, each '
                            "'topic:package/msg/Type:field' (e.g. "
                            "'battery_state:sensor_msgs/msg/BatteryState:current', "
                            "'cmd_vel:geometry_msgs/msg/Twist:abs(linear.x)'); learned and "
                            'compensated live. Empty: none.', {'dynamic_typing': True}),
    'learn_compensation': (DEFAULTS.learn_compensation,
                           "Learn the robot's own field (K per input, c per degC) while it "
                           'works; adopted only when better on held-out readings.', {}),
    'compensation_timeout': (60.0, 'Seconds of readings ~/learn_compensation learns for at '
                                   'most before it answers with what it still needs.',
                             {'floating_point_range': _float_range(5.0, MAX_WINDOW_S)}),
}
SESSION_FIELDS = {f.name for f in fields(SessionSettings)}


def session_settings(values: Mapping[str, object]) -> SessionSettings:
    """The SessionSettings of these parameter values (the entries sharing their field names)."""
    settings = {k: v for k, v in values.items() if k in SESSION_FIELDS}
    inputs = settings.get('interference_inputs', ())
    if inputs is None or (isinstance(inputs, (list, tuple, bytes)) and not inputs):
        settings['interference_inputs'] = ()  # rclpy: an empty list has no type (None, b'')
    elif isinstance(inputs, (list, tuple)):
        settings['interference_inputs'] = tuple(inputs)
    return SessionSettings(**settings)


def parameter_problems(values: Mapping[str, object], at_run_time: bool = False) -> list[str]:
    """Everything wrong with these parameter values (``at_run_time``: half a location waits for
    the other instead of being refused)."""
    problems = session_settings(values).problems()
    problems += input_topic_problems(values['interference_inputs'])
    problems += turn_settings_from(values).problems()
    try:
        resolve_calibration_path(str(values['calibration_file']))
    except CalibrationFileError as error:
        problems.append(f'calibration_file: {error}')
    problems += parameter_location_problems(values['latitude'], values['longitude'],
                                            values['altitude'], incomplete_ok=at_run_time)
    return problems
