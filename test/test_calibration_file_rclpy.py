# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibration file as rcl reads it: ``--params-file`` on a real rclpy node types every value
as the node declares it, and applies exactly the sections ``section_matches`` says (the evidence
behind test_calibration_file.py's RCL_MATCHES, re-measured on every run). The file's own tests,
without ROS, are test_calibration_file.py."""

from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.store.calibration_file import (
    calibration_from_parameters,
    calibration_yaml,
    load_calibration,
    read_calibration_file,
    save_calibration,
)

rclpy = pytest.importorskip('rclpy')
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_calibration_file import METADATA, NODES, RCL_MATCHES, fitted_calibration  # noqa: E402


def rclpy_parameters(path, node_name, declared):
    """The ``calibration.*`` values a real rclpy node gets from ``--params-file path``."""
    namespace, _, name = node_name.rpartition('/')
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context)
    try:
        node = Node(name, namespace=namespace or '/', context=context)
        try:
            return {key: node.declare_parameter(f'calibration.{key}', kind).value
                    for key, kind in declared.items()}
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize(('key', 'node_name'), [
    ('mag_calibrator', '/mag_calibrator'),  # the key older versions wrote: root namespace only
    ('/robot1/mag_calibrator', '/robot1/mag_calibrator'),  # what the node writes now
    ('/**', '/robot1/sub/mag_calibrator'),
])
def test_rclpy_loads_the_file_as_a_params_file(tmp_path, key, node_name):
    """rcl's own YAML parser must type every value as the node declares it."""
    calibration = Calibration(  # integral values: the int-vs-double trap (F in tesla is not)
        np.array([0.0, -0.0, 0.0]), np.diag([2.0, 1.0, 1.0]), 5e-5, 'full',
        {**METADATA, 'frame_id': 'on', 'condition_number': 1.0},
        rotation=[[0, -1, 0], [1, 0, 0], [0, 0, 1]],
    )
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, calibration, node_name=key)
    values = rclpy_parameters(path, node_name, {
        'offset': Parameter.Type.DOUBLE_ARRAY,
        'matrix': Parameter.Type.DOUBLE_ARRAY,
        'rotation': Parameter.Type.DOUBLE_ARRAY,
        'field_strength': Parameter.Type.DOUBLE,
        'model': Parameter.Type.STRING,
        'samples': Parameter.Type.INTEGER,
        'time': Parameter.Type.STRING,
        'frame_id': Parameter.Type.STRING,
        'condition_number': Parameter.Type.DOUBLE,
    })
    assert values['frame_id'] == 'on' and values['samples'] == 100
    rebuilt = calibration_from_parameters(
        values['offset'], values['matrix'], values['field_strength'], values['model'],
        {'rotation': values['rotation']},
    )
    np.testing.assert_array_equal(rebuilt.offset, calibration.offset)
    np.testing.assert_array_equal(rebuilt.matrix, calibration.matrix)
    assert rebuilt.field_strength == 5e-5
    assert rebuilt.rotation.reshape(9).tolist() == [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    assert read_calibration_file(path, node_name).notes == ()  # it is this node's section


def test_rclpy_applies_sections_exactly_as_section_matches_says(tmp_path):
    """The evidence behind RCL_MATCHES and the merge order, re-measured on every run."""
    double = {'field_strength': Parameter.Type.DOUBLE}
    for key, expected in RCL_MATCHES.items():
        path = tmp_path / 'key.yaml'
        save_calibration(path, fitted_calibration(), node_name=key)
        applied = {node for node in NODES
                   if rclpy_parameters(path, node, double)['field_strength'] is not None}
        assert applied == expected, key
    for order in ((('/**', 1e-5), ('/robot1/mag_calibrator', 2e-5)),
                  (('/robot1/mag_calibrator', 2e-5), ('/**', 1e-5))):
        path = tmp_path / 'merged.yaml'
        path.write_text(''.join(
            calibration_yaml(Calibration(np.zeros(3), np.eye(3), strength), key)
            for key, strength in order))
        ours = load_calibration(path, '/robot1/mag_calibrator').field_strength
        assert ours == rclpy_parameters(path, '/robot1/mag_calibrator', double)['field_strength']
