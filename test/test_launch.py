# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
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
def launch_module(tmp_path, monkeypatch):
    """The launch file as a module, with the package in an ament index of its own."""
    index = tmp_path / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'mag_calibrator_ros').touch()
    (tmp_path / 'share' / 'mag_calibrator_ros').mkdir()
    (tmp_path / 'share' / 'mag_calibrator_ros' / 'config').symlink_to(REPO_ROOT / 'config')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    spec = spec_from_file_location('mag_calibrator_launch', LAUNCH_FILE)
    module = module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def description(launch_module):
    return launch_module.generate_launch_description()


ARGUMENTS = {'backend', 'calibration_file', 'namespace', 'driver_params_file',
             'calibrator_params_file', 'sim.hard_iron_ut', 'sim.soft_iron', 'sim.noise_ut',
             'sim.motion', 'use_sim_time', 'rviz'}


def launched(description, **arguments):
    """The nodes the launch would start for these arguments (name: node); its lines to the
    user are in ``launched.said``."""
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    from launch import LaunchContext

    context = LaunchContext()
    for entity in description.entities:
        if isinstance(entity, DeclareLaunchArgument):
            value = arguments.get(entity.name, entity.default_value)
            context.launch_configurations[entity.name] = (
                value if isinstance(value, str) else ''.join(s.perform(context) for s in value))
    from launch.actions import LogInfo

    nodes, launched.said = {}, []
    for function in [e for e in description.entities if isinstance(e, OpaqueFunction)]:
        for action in function.execute(context) or []:
            if isinstance(action, LogInfo):
                launched.said.append(''.join(s.perform(context) for s in action.msg))
            else:
                nodes[action.node_executable] = action
    return nodes


def files_and_given(node) -> tuple[list[str], dict[str, object]]:
    """A launch_ros Node's params files, and the name: value parameters given beside them."""
    from launch import LaunchContext

    context, files, values = LaunchContext(), [], {}
    for entry in node._Node__parameters:
        if isinstance(entry, dict):
            for key, value in entry.items():
                name = ''.join(s.perform(context) for s in key)
                if isinstance(value, (list, tuple)) and value and hasattr(value[0], 'perform'):
                    value = yaml.safe_load(''.join(s.perform(context) for s in value))
                values[name] = list(value) if isinstance(value, tuple) else value
        else:  # a launch_ros ParameterFile
            files.append(str(entry.evaluate(context)))
    return files, values


def test_every_argument_is_declared_and_in_the_docstring(description):
    from launch.actions import DeclareLaunchArgument

    declared = {a.name for a in description.entities if isinstance(a, DeclareLaunchArgument)}
    assert declared == ARGUMENTS
    text = LAUNCH_FILE.read_text()
    assert [name for name in ARGUMENTS if f'``{name}``' not in text] == []


def test_launch_starts_the_driver_and_a_calibrator_with_its_own_file(description):
    nodes = launched(description)
    assert set(nodes) == {'icm20948_driver', 'mag_calibrator'}  # no rviz2 unless asked
    files, given = files_and_given(nodes['icm20948_driver'])
    assert [Path(f).name for f in files] == ['icm20948_driver.yaml']
    assert given == {'use_sim_time': False}  # backend and sim.*: the params file's
    nodes = launched(description, namespace='robot1')
    for node in nodes.values():
        assert node._Node__node_namespace == 'robot1'
    files, given = files_and_given(nodes['mag_calibrator'])
    assert [Path(f).name for f in files] == ['mag_calibrator.yaml']
    assert given == {'use_sim_time': False}  # only the config file: the node's own default
    _, given = files_and_given(
        launched(description, calibration_file='/data/mag.yaml')['mag_calibrator'])
    assert given == {'calibration_file': '/data/mag.yaml', 'use_sim_time': False}


def test_simulator_arguments_params_files_and_sim_time_reach_the_nodes(description, tmp_path):
    nodes = launched(description, backend='sim', use_sim_time='true',
                     driver_params_file=str(tmp_path / 'driver.yaml'),
                     calibrator_params_file=str(tmp_path / 'calibrator.yaml'),
                     **{'sim.hard_iron_ut': '[120, -80.0, 60]', 'sim.noise_ut': '1',
                        'sim.soft_iron': '[1.1, 0, 0, 0, 0.9, 0, 0, 0, 1]', 'sim.motion': 'yaw'})
    files, given = files_and_given(nodes['icm20948_driver'])
    assert files == [str(tmp_path / 'driver.yaml')]
    assert given == {'backend': 'sim', 'use_sim_time': True, 'sim.motion': 'yaw',
                     'sim.hard_iron_ut': [120.0, -80.0, 60.0], 'sim.noise_ut': 1.0,
                     'sim.soft_iron': [1.1, 0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0, 1.0]}
    assert all(isinstance(v, float) for v in given['sim.hard_iron_ut'])  # doubles, as declared
    files, given = files_and_given(nodes['mag_calibrator'])
    assert files == [str(tmp_path / 'calibrator.yaml')] and given == {'use_sim_time': True}


def test_rviz_follows_the_namespace(launch_module, monkeypatch):
    monkeypatch.setattr(launch_module, 'rviz2_installed', lambda: True)
    nodes = launched(launch_module.generate_launch_description(), namespace='robot1',
                     rviz='true')
    rviz = nodes['rviz2']
    (path,) = [a for a in _arguments(rviz) if a.endswith('.rviz')]
    text = Path(path).read_text()
    Path(path).unlink()
    for view in ('raw', 'corrected', 'markers'):
        assert f'Value: /robot1/mag_calibrator/view/{view}' in text
    assert 'Value: /mag_calibrator/view/' not in text


def test_rviz_asked_for_where_it_is_not_installed_is_a_line_and_the_nodes_still_start(
        launch_module, monkeypatch):
    """Launch stopped on 'package rviz2 not found' after starting the nodes, and left them
    running as orphans (issue #46)."""
    monkeypatch.setattr(launch_module, 'rviz2_installed', lambda: False)
    nodes = launched(launch_module.generate_launch_description(), rviz='true')
    assert set(nodes) == {'icm20948_driver', 'mag_calibrator'}
    (line,) = launched.said
    assert 'rviz2 is not installed' in line and 'ros-jazzy-rviz2' in line


def test_each_node_is_told_the_launch_pid_it_stops_with(description):
    import os

    from mag_calibrator_ros.nodes.runtime import LAUNCH_PID_ENV

    for node in launched(description).values():
        environment = {''.join(s.perform(None) for s in key): ''.join(
            s.perform(None) for s in value) for key, value in node.additional_env}
        assert environment == {LAUNCH_PID_ENV: str(os.getpid())}


def _arguments(node) -> list[str]:
    from launch import LaunchContext

    context = LaunchContext()
    return [argument if isinstance(argument, str) else
            ''.join(s.perform(context) for s in argument) for argument in node._Node__arguments]


def test_the_rviz_config_for_a_namespace_moves_its_three_topics_and_nothing_else(launch_module):
    module = launch_module
    shipped = (REPO_ROOT / 'config' / 'mag_calibrator.rviz').read_text()
    assert module.namespaced_rviz_config(shipped, '') == shipped
    assert module.namespaced_rviz_config(shipped, '/') == shipped
    for namespace in ('robot1', '/robot1', '/robot1/', 'fleet/robot2'):
        moved = module.namespaced_rviz_config(shipped, namespace)
        prefix = '/' + namespace.strip('/')
        lines = list(zip(shipped.splitlines(), moved.splitlines(), strict=True))
        changed = [(a, b) for a, b in lines if a != b]
        assert len(changed) == 3
        for before, after in changed:
            assert after == before.replace('/mag_calibrator/', f'{prefix}/mag_calibrator/')
    yaml.safe_load(module.namespaced_rviz_config(shipped, 'robot1'))  # still a valid YAML file
