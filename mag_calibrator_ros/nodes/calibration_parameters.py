# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""``calibration.*``: the calibration in force, mirrored as the node's parameters.

``ros2 param get/dump`` read the calibration in force there, and a dump (or a saved calibration
file: the same ROS params format) given back with ``--params-file`` is the calibration at
start-up, even when ``calibration_file`` holds another one (said at start-up:
``shadowed_file_note``). Only the node itself changes them afterwards: a set from outside is
refused, since a calibration goes in force through ``~/calibrate`` or ``~/load``, where it is
checked.
"""

from __future__ import annotations

from collections.abc import Mapping
import datetime
import math
from pathlib import Path

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    calibration_from_parameters,
    calibration_parameters,
    default_load_path,
    resolve_calibration_path,
)

CALIBRATION_METADATA_KEYS = (
    'residual_rms_pct', 'coverage', 'samples', 'time', 'frame_id', 'units', 'source',
    'plane_normal', 'unobserved', 'alignment_angle_deg', 'dip_deg', 'dip_std_deg',
    'static_samples', 'declination_deg',
    # a ground robot's planar fit levelled by gravity (what a refinement weighs in)
    'levelled_by_gravity', 'levelled_dip_deg', 'levelled_offset_normal_std',
    # the robot's own field (K u + c (T - T0)) and when it was learned
    'interference_inputs', 'interference', 'temperature_coefficient', 'reference_temperature',
    'compensation_time', 'compensation_removed_pct', 'compensation_readings',
    'compensation_interference_pct',
)
"""Metadata a saved file may carry (declared so --params-file keeps it), and the optional
compensation (``calibration_file``'s COMPENSATION_KEYS)."""
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


def calibration_from(parameters: Mapping[str, object]) -> Calibration:
    """The calibration that ``calibration.*`` values describe; raises CalibrationError,
    ValueError or TypeError saying what is wrong."""
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


def parameters_given(given: Mapping[str, object]) -> bool:
    """Whether --params-file gave a calibration (``calibration.*`` beyond metadata): it is the
    start-up calibration then, whatever ``calibration_file`` holds."""
    return any(name in given for name in CALIBRATION_PARAMETERS)


def startup_load_path(calibration_file: Path, default_file: Path, node_name: str) -> Path:
    """The file the start-up calibration comes from when no ``calibration.*`` were given.

    ``calibration_file`` left at the per-node default (``default_file``) reads
    :func:`default_load_path`: the node's own file, or the old shared one for a single robot.
    """
    if calibration_file == resolve_calibration_path(default_file):
        return default_load_path(node_name)
    return calibration_file


def shadowed_file_note(in_force: Calibration, on_file: Calibration | None, path: Path
                       ) -> tuple[str, str] | None:
    """(level, text) when ``calibration.*`` from --params-file put ``in_force`` while the
    calibration file at ``path`` holds another calibration (``on_file``; None: no file): a
    ``ros2 param dump`` given back would otherwise hide every later ``~/save`` for good. The
    fit times (``time`` metadata) tell which one is newer; a warning unless the file's is older.
    """
    if on_file is None or _same_calibration(in_force, on_file):
        return None
    given_time, file_time = (_fit_time(c) for c in (in_force, on_file))
    fix = ('the parameters win at every start: to use the file, remove calibration.* from '
           'the --params-file (or call ~/load now); to keep the parameters, call ~/save')
    if given_time is not None and file_time is not None and file_time <= given_time:
        return 'info', (f'{path} holds an older calibration (fitted {file_time:%Y-%m-%d %H:%M}) '
                        f'than the calibration.* parameters in force (fitted '
                        f'{given_time:%Y-%m-%d %H:%M}); {fix}')
    if given_time is not None and file_time is not None:
        what = (f'a newer calibration (fitted {file_time:%Y-%m-%d %H:%M}) than the '
                f'calibration.* parameters in force (fitted {given_time:%Y-%m-%d %H:%M})')
    else:
        what = ('a different calibration from the calibration.* parameters in force (no fit '
                'time on both to tell which is newer)')
    return 'warning', f'{path} holds {what}: {fix}'


def _same_calibration(a: Calibration, b: Calibration) -> bool:
    tolerance = 1e-9 * max(a.field_strength, b.field_strength, 1e-300)
    return (a.model == b.model
            and np.allclose(a.offset, b.offset, rtol=1e-9, atol=tolerance)
            and np.allclose(a.matrix, b.matrix, rtol=1e-9, atol=1e-12)
            and np.allclose(a.rotation, b.rotation, rtol=1e-9, atol=1e-12)
            and math.isclose(a.field_strength, b.field_strength, rel_tol=1e-9))


def _fit_time(calibration: Calibration) -> datetime.datetime | None:
    """When the calibration was fitted (``time``: ISO 8601 UTC), None when it does not say."""
    try:
        moment = datetime.datetime.fromisoformat(str(calibration.metadata['time']))
    except (KeyError, ValueError):
        return None
    return moment if moment.tzinfo else moment.replace(tzinfo=datetime.UTC)


class CalibrationParameters:
    """Declares ``calibration.*`` on ``node`` and keeps them showing the calibration in force.

    ``given``: what --params-file set at start-up (empty for a dump of an uncalibrated node).
    """

    def __init__(self, node: Node) -> None:
        self._node = node
        self._showing = False
        self.shown: Calibration | None = None
        """The calibration the parameters show now (compared by identity)."""
        self.given = self._declare()

    def _declare(self) -> dict[str, object]:
        """Declare ``calibration.*``; returns what --params-file gave.

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
            value = self._node.declare_parameter(name, None, descriptor).value
            if value is not None:
                given[name] = value
        if given.get('calibration.model') == NO_CALIBRATION['calibration.model']:
            return {}  # a dump of an uncalibrated node: no calibration given
        return given

    def refusal(self, parameters: list[Parameter]) -> SetParametersResult | None:
        """The answer to a set of ``calibration.*`` from outside the node; None for any other."""
        if any(p.name.startswith('calibration.') for p in parameters) and not self._showing:
            return SetParametersResult(successful=False, reason=CALIBRATION_READ_ONLY)
        return None

    def show(self, calibration: Calibration | None) -> None:
        """Set ``calibration.*`` to ``calibration`` (``ros2 param get/dump`` read it), metadata it
        does not carry left unset, never NOT_SET: a dump loads back as given."""
        node = self._node
        self.shown = calibration
        values = dict(NO_CALIBRATION)
        if calibration is not None:
            try:
                values = calibration_parameters(calibration)
            except CalibrationFileError as error:
                node.get_logger().warning(f'calibration.* not updated: {error}')
                return
        parameters = []
        for name, value in values.items():
            try:
                parameters.append(Parameter(name, value=value))
            except TypeError:  # metadata no parameter can hold (a mixed list ...)
                continue
        kept = {parameter.name for parameter in parameters}
        self._showing = True  # our own change: refusal() lets it through
        try:
            for key in CALIBRATION_METADATA_KEYS:
                name = f'calibration.{key}'
                if name not in kept and node.has_parameter(name):
                    node.undeclare_parameter(name)
            for parameter in parameters:
                if not node.has_parameter(parameter.name):
                    node.declare_parameter(parameter.name, None, ParameterDescriptor(
                        description='Calibration metadata; informational.',
                        dynamic_typing=True))
            node.set_parameters(parameters)
        finally:
            self._showing = False
