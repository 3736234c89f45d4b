"""The launch file (where launch_ros exists: apt ROS, or the ros2 CLI installed into the venv)."""

from importlib.util import module_from_spec, spec_from_file_location
from pathlib import Path

import pytest
import yaml

pytest.importorskip('launch_ros', reason='launch_ros has no PyPI wheel; runs on apt ROS installs')
pytest.importorskip('launch')

REPO_ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO_ROOT / 'launch' / 'mag_calibrator.launch.py'


@pytest.fixture
def description(tmp_path, monkeypatch):
    """The launch description, with the package in an ament index of its own."""
    index = tmp_path / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'mag_calibrator_ros').touch()
    (tmp_path / 'share' / 'mag_calibrator_ros').mkdir()
    (tmp_path / 'share' / 'mag_calibrator_ros' / 'config').symlink_to(REPO_ROOT / 'config')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    spec = spec_from_file_location('mag_calibrator_launch', LAUNCH_FILE)
    module = module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def calibrator_parameters(description, **arguments):
    """The calibrator node the launch would start for these arguments, and its parameters."""
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    from launch import LaunchContext

    context = LaunchContext()
    for entity in description.entities:
        if isinstance(entity, DeclareLaunchArgument):
            value = arguments.get(entity.name, entity.default_value)
            context.launch_configurations[entity.name] = (
                value if isinstance(value, str) else ''.join(s.perform(context) for s in value))
    (function,) = [e for e in description.entities if isinstance(e, OpaqueFunction)]
    (node,) = function.execute(context)
    return node, node._Node__parameters


def test_launch_starts_the_driver_and_a_calibrator_with_its_own_file(description):
    from launch.actions import DeclareLaunchArgument
    from launch_ros.actions import Node

    arguments = {a.name for a in description.entities if isinstance(a, DeclareLaunchArgument)}
    assert {'backend', 'calibration_file', 'namespace'} <= arguments
    (driver,) = [e for e in description.entities if isinstance(e, Node)]
    assert driver.node_executable == 'icm20948_driver'
    node, parameters = calibrator_parameters(description, namespace='robot1')
    assert node.node_executable == 'mag_calibrator'
    assert given(parameters) == {}  # only the config file: the node's own per-node default
    node, parameters = calibrator_parameters(description, calibration_file='/data/mag.yaml')
    assert given(parameters) == {'calibration_file': '/data/mag.yaml'}


def given(parameters) -> dict[str, str]:
    """The name: value parameters of a launch_ros Node (normalised to substitutions)."""
    from launch import LaunchContext

    context, values = LaunchContext(), {}
    for entry in parameters:
        if isinstance(entry, dict):
            for key, value in entry.items():
                text = ''.join(s.perform(context) for s in value)
                values[''.join(s.perform(context) for s in key)] = yaml.safe_load(text)
    return values
