# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field in ``mag_calibrator_fit``: its inputs read from a recording, learned
by the live calibrator's own ``CompensationLearner``, and reported.

A recording that logs the battery or motor current and the sensor temperature beside the
magnetometer (text columns named by the header or by option; a bag's ``sensor_msgs/BatteryState``
and ``sensor_msgs/Temperature`` topics, paired by stamp) is streamed with them, each row's
values handed to the session as the node's ``imu/temperature`` and ``interference_inputs``
subscriptions hand theirs over (``nodes/inputs.py``): the same learner, the same evidence rule,
so the offline K, c and T0 are what the robot would learn from the same drive. Once K and c
are learned, the static calibration is fitted on a second pass over every reading without
them (:func:`without_own_field`), as a node with them in force from its first reading would
hold it: the first pass's buffer chose and merged its readings while K and c were still being
learned (each compensation put in force moves them, but chose none of them).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import math
from typing import Any

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration, Compensation
from mag_calibrator_ros.calibration.live.compensation import input_columns
from mag_calibrator_ros.calibration.live.jobs import kept_compensation
from mag_calibrator_ros.calibration.live.report import interference_text
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.tools.recording_value import Recording

HELP = (
    'Learn the field the robot makes itself: K per unit of each current and c per degree of '
    'the sensor temperature (corrected = R M (raw - b - K u - c (T - T0))), as the node learns '
    'them live, from readings taken while the current and the temperature varied and the robot '
    'turned. Text: columns whose header is current, battery_current, motor_current, *_current '
    '(inputs) or temperature, temp, T (C) (the sensor temperature in degrees Celsius; a header '
    'in K or F is converted); a bag: its only sensor_msgs/BatteryState topic (current) and its '
    'only sensor_msgs/Temperature topic, each paired with the reading nearest its stamp. Only '
    "with the buffer (not --all). K is applied to the node's interference_inputs in the "
    'order the file names them: list the topics carrying these inputs in that order. Once K '
    'or c is learned, the static calibration comes from a second pass over every reading '
    'without them.')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the robot's own field (their own group in --help)."""
    group = parser.add_argument_group("the robot's own field (current, temperature)", HELP)
    group.add_argument('--input-columns', metavar='NAME[,NAME]', default=None,
                       help='text input: the interference inputs (e.g. motor currents) by '
                       "header name or zero-based index; '' for none (default: by header name)")
    group.add_argument('--temperature-column', metavar='NAME', default=None,
                       help="text input: the sensor temperature's column (degrees Celsius) by "
                       "header name or index; '' for none (default: by header name)")
    group.add_argument('--battery-topic', metavar='TOPIC', default=None,
                       help="bag input: the sensor_msgs/BatteryState topic; '' for none "
                       '(default: the only one)')
    group.add_argument('--temperature-topic', metavar='TOPIC', default=None,
                       help="bag input: the sensor_msgs/Temperature topic; '' for none "
                       '(default: the only one)')
    group.add_argument('--no-compensation', action='store_true',
                       help='ignore those columns and topics: the static calibration only')


def reader_option(args: argparse.Namespace, bag: bool) -> tuple[str | None, str | None] | None:
    """What ``read_recording(compensation=...)`` reads: None with --no-compensation."""
    if args.no_compensation:
        return None
    if bag:
        return args.battery_topic, args.temperature_topic
    return args.input_columns, args.temperature_column


def text_options(args: argparse.Namespace) -> list[str]:
    """The text-only options given (refused with a bag)."""
    return [option for option, value in (('--input-columns', args.input_columns),
                                         ('--temperature-column', args.temperature_column))
            if value is not None]


def bag_options(args: argparse.Namespace) -> list[str]:
    """The bag-only options given (refused with text)."""
    return [option for option, value in (('--battery-topic', args.battery_topic),
                                         ('--temperature-topic', args.temperature_topic))
            if value is not None]


def learning_settings(settings: SessionSettings, recording: Recording) -> SessionSettings:
    """``settings`` for a session that learns the recording's own field: the temperature on
    when logged (its inputs are the session's ``input_names``: ``recording.input_names``)."""
    return replace(settings, use_temperature=recording.temperature is not None)


def feed(session: CalibrationSession, recording: Recording, index: int, stamp_ns: int) -> None:
    """Row ``index``'s temperature and inputs, before its reading, as the node's subscriptions
    hand them over (NaN ones are not handed over: the learner pairs the nearest fresh one)."""
    if recording.temperature is not None:
        celsius = float(recording.temperature[index])
        if math.isfinite(celsius):
            session.process_temperature(stamp_ns, celsius)
    if recording.inputs is not None:
        for column, value in enumerate(recording.inputs[index].tolist()):
            if math.isfinite(value):
                session.process_input(column, stamp_ns, value)


def with_learned(calibration: Calibration | None, session: CalibrationSession | None
                 ) -> Calibration | None:
    """The final fit with the compensation the session learned (the buffer it fitted was
    compensated by it, so it belongs with it)."""
    if calibration is None or session is None or session.calibration is None:
        return calibration
    return kept_compensation(calibration, session.calibration)


def learned(session: CalibrationSession) -> Compensation | None:
    """The compensation the session learned and holds in force at the recording's end (None
    when it learned none: a calibration it started from may bring its own)."""
    if session.calibration is None or not session.report().counts.adoptions.get('compensation'):
        return None
    return session.calibration.compensation


def without_own_field(recording: Recording, compensation: Compensation) -> np.ndarray:
    """The recording's readings without the robot's own field ``compensation`` models: each
    row's inputs and temperature, or the latest before it where the row has none (as the node
    holds the latest sample); none before the first. Inputs are matched to the recording's
    as the node matches them (``input_columns``); a term with no input here removes nothing."""
    inputs = temperature = None
    columns = input_columns(compensation.inputs, recording.input_names)
    if recording.inputs is not None and len(compensation.inputs) and columns is not None:
        inputs = _latest(recording.inputs[:, columns])
    if recording.temperature is not None:
        temperature = _latest(recording.temperature.reshape(-1, 1))[:, 0]
    return recording.samples - compensation.field(inputs, temperature)


def _latest(values: np.ndarray) -> np.ndarray:
    """(n, k): each NaN replaced by the latest finite value above it in its column."""
    if values.ndim != 2:
        raise ValueError(f'_latest takes (n, k) columns, not an array of shape {values.shape}')
    known = np.isfinite(values)
    rows = np.where(known, np.arange(len(values))[:, None], -1)
    np.maximum.accumulate(rows, axis=0, out=rows)
    filled = np.take_along_axis(values, np.maximum(rows, 0), axis=0)
    filled[rows < 0] = math.nan
    return filled


def summary(recording: Recording, calibration: Calibration | None,
            session: CalibrationSession | None) -> dict[str, Any] | None:
    """The --json 'compensation' object: the inputs, K, c, T0, the share removed, or what the
    recording lacked; None when the recording logs no input."""
    if recording.inputs is None and recording.temperature is None and not (
            recording.input_problems):
        return None
    found: dict[str, Any] = {
        'inputs': list(recording.input_names),
        'temperature': recording.temperature is not None,
        'problems': list(recording.input_problems),
        'learned': False,
    }
    if recording.temperature is not None:
        usable = recording.temperature[np.isfinite(recording.temperature)]
        found['temperature_range_degC'] = [float(usable.min()), float(usable.max())]
    compensation = None if calibration is None else calibration.compensation
    found['learned'] = session is not None and learned(session) is not None
    if compensation is not None:  # learned, or a file's (mag_calibrator_fit --calibration)
        found['interference'] = {name: [float(v) for v in compensation.interference[:, j]]
                                 for j, name in enumerate(compensation.inputs)}
        found['temperature_coefficient'] = [float(v)
                                            for v in compensation.temperature_coefficient]
        found['reference_temperature_degC'] = compensation.reference_temperature
        found['removed_pct'] = calibration.metadata.get('compensation_removed_pct')  # type: ignore[union-attr]
        found['readings'] = calibration.metadata.get('compensation_readings')  # type: ignore[union-attr]
        found['interference_pct'] = calibration.metadata.get('compensation_interference_pct')  # type: ignore[union-attr]
    if session is None:
        found['needs'] = ('the compensation is learned by the buffer as the node does; drop '
                          '--all to learn it')
    else:
        found['needs'] = session.report().compensation_needs or (
            '' if found['learned'] else 'no compensation fit ran: the recording needs a '
            'calibration in force first and at least 200 readings with the inputs after it')
    return found


def lines(found: dict[str, Any] | None, units: str) -> list[str]:
    """The readable report's lines of the robot's own field."""
    if found is None:
        return []
    logged = [f"inputs {', '.join(found['inputs'])}"] if found['inputs'] else []
    if found['temperature']:
        low, high = found['temperature_range_degC']
        logged.append(f'temperature {low:.1f}..{high:.1f} degC')
    out = [f"own field {'; '.join(logged) or 'no usable input'}"]
    out += [f'          problem: {problem}' for problem in found['problems']]
    if 'interference' in found:
        for name, column in found['interference'].items():
            out.append(f"K         [{'  '.join(f'{v:>12.6g}' for v in column)} ]  "
                       f'{units} per unit of {name}')
        t0 = found['reference_temperature_degC']
        around = '' if t0 is None else f' around T0 {t0:.2f} degC'
        c = '  '.join(f'{v:>12.6g}' for v in found['temperature_coefficient'])
        out.append(f'c         [{c} ]  {units} per degC{around}')
        removed = found['removed_pct']
        if removed is not None:
            out.append(f'          removes {removed:.2f} % of the field (RMS over the readings '
                       'it was learned from)')
        if found.get('interference_pct') is not None:
            out.append('          ' + interference_text(found['interference_pct'])
                       .removeprefix('; '))
        if any(':' not in name for name in found['interference']):
            out.append("          on the robot: the node's interference_inputs name the topics "
                       'carrying these inputs, in this order (topic:package/msg/Type:field)')
    if not found['learned']:
        out.append('          not learned: ' + (found['needs'] or 'nothing determined'))
    if found['learned'] and found['needs']:
        out.append(f"          still undetermined: {found['needs']}")
    return out


__all__ = ['add_arguments', 'bag_options', 'feed', 'learned', 'learning_settings', 'lines',
           'reader_option', 'summary', 'text_options', 'with_learned', 'without_own_field']
