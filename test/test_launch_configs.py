# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Every shipped config/*.yaml reaches its node in a namespace (issue #21): `ros2 launch ...
namespace:=robot1` and `-r __ns:=/robot1` rename the node /robot1/<name>, and a params file keyed
by the bare node name would then be ignored without a word."""

import math
from pathlib import Path

import pytest
import rclpy
import yaml

from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode

CONFIG = Path(__file__).resolve().parents[1] / 'config'
# Each shipped file, its node, and edits away from the defaults that the node must then run with.
SHIPPED = {
    'icm20948_driver.yaml': (Icm20948DriverNode, {'backend: smbus2': 'backend: sim',
                                                  'rate_hz: 100': 'rate_hz: 50'}),
    'mag_calibrator.yaml': (MagCalibratorNode, {'buffer_size: 100': 'buffer_size: 150',
                                                'model: auto': 'model: sphere'}),
}


def test_every_shipped_params_file_is_listed_here():
    assert sorted(p.name for p in CONFIG.glob('*.yaml')) == sorted(SHIPPED)


@pytest.mark.parametrize('namespace', ['/robot1', '/fleet/robot2'])
@pytest.mark.parametrize('file_name', sorted(SHIPPED))
def test_a_shipped_params_file_applies_to_its_node_in_a_namespace(tmp_path, file_name, namespace):
    node_class, edits = SHIPPED[file_name]
    text = (CONFIG / file_name).read_text()
    for old, new in edits.items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    edited = tmp_path / file_name
    edited.write_text(text)
    (documented,) = [entry['ros__parameters'] for entry in yaml.safe_load(text).values()]
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '-r', f'__ns:={namespace}', '--params-file', str(edited)],
               context=context)
    try:
        node = node_class(context=context)
        try:
            assert node.get_namespace() == namespace
            for name, value in documented.items():
                got = node.get_parameter(name).value
                nan = isinstance(value, float) and math.isnan(value)
                assert (math.isnan(got) if nan else got == value), name
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
