"""The calibration file: ROS 2 parameters YAML, exact round trip, atomic save, validated load."""

import os
import re

import numpy as np
import pytest
import yaml

from mag_calibrator_ros.calibration import calibration_file
from mag_calibrator_ros.calibration.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.calibration_file import (
    CalibrationFileError,
    calibration_from_parameters,
    calibration_yaml,
    load_calibration,
    save_calibration,
)

SOFT_IRON = np.array([[1.0312, 0.0417, -0.0123], [0.0417, 0.9871, 0.0089], [-0.0123, 0.0089, 1.1]])
METADATA = {
    'residual_rms_pct': 0.8123,
    'coverage': 0.95,
    'samples': 100,
    'time': '2026-11-22T00:30:00Z',
    'frame_id': 'imu_link',
    'units': 'T',
}


def fitted_calibration(**metadata):
    return Calibration(
        np.array([1.234e-5, -2.5e-6, 3.0e-7]), SOFT_IRON, 4.9e-5, 'full', {**METADATA, **metadata}
    )


def parameters_of(text):
    return yaml.safe_load(text)['mag_calibrator']['ros__parameters']['calibration']


# -- round trip and format ------------------------------------------------------------------------


def test_round_trip_is_exact(tmp_path):
    calibration = fitted_calibration(
        unobserved=('z',), flags=[True, False], counts=np.array([3, 4]), nested={'a': 1.5}
    )
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, calibration)
    loaded = load_calibration(path)
    np.testing.assert_array_equal(loaded.offset, calibration.offset)
    np.testing.assert_array_equal(loaded.matrix, calibration.matrix)
    assert loaded.field_strength == calibration.field_strength
    assert loaded.model == 'full'
    assert loaded.metadata == {
        **METADATA, 'unobserved': ['z'], 'flags': [True, False], 'counts': [3, 4],
        'nested': {'a': 1.5},
    }


def test_the_file_has_the_documented_layout(tmp_path):
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, fitted_calibration())
    document = yaml.safe_load(path.read_text())
    assert list(document) == ['mag_calibrator']
    assert list(document['mag_calibrator']) == ['ros__parameters']
    section = document['mag_calibrator']['ros__parameters']['calibration']
    assert section['matrix'] == SOFT_IRON.reshape(9).tolist()  # row-major
    assert section['field_strength'] == 4.9e-5 and section['model'] == 'full'
    assert section['samples'] == 100 and isinstance(section['samples'], int)


@pytest.mark.parametrize(
    'value', [1.0, 0.0, -3.0, 50.0, 1e17, 1e-7, 5e-05, 123456789.0, 1e300, -2.5e-310]
)
def test_doubles_always_carry_a_decimal_point_or_exponent(value):
    calibration = Calibration([value, 0.0, 1.0], np.eye(3), abs(value) or 1.0, 'sphere')
    text = calibration_yaml(calibration)
    numbers = re.findall(r'(?:offset|matrix|field_strength): \[?([^\]\n]*)', text)
    for number in ', '.join(numbers).split(', '):
        assert re.fullmatch(r'-?\d+\.\d*(e[-+]\d+)?', number), number
    section = parameters_of(text)
    assert all(type(item) is float for item in section['offset'] + section['matrix'])
    assert section['offset'][0] == value
    assert type(section['field_strength']) is float


@pytest.mark.parametrize('text', ['on', 'y', 'no', 'null', '~', '1e5', '0x10', '1.0', '', 'µT',
                                  'a "quoted" \\ word', 'line\nbreak', '012'])
def test_strings_stay_strings(tmp_path, text):
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, fitted_calibration(frame_id=text))
    assert parameters_of(path.read_text())['frame_id'] == text
    assert load_calibration(path).metadata['frame_id'] == text


def test_values_yaml_cannot_type_are_left_out():
    section = parameters_of(calibration_yaml(fitted_calibration(nothing=None, empty=[])))
    assert 'nothing' not in section and 'empty' not in section


def test_mixed_number_lists_become_doubles():
    section = parameters_of(calibration_yaml(fitted_calibration(mixed=[1, 2.5])))
    assert section['mixed'] == [1.0, 2.5] and type(section['mixed'][0]) is float


@pytest.mark.parametrize(
    ('metadata', 'message'),
    [({'offset': [0, 0, 0]}, 'overwrite'), ({'bad key': 1}, 'not a valid ROS parameter name'),
     ({'nested': {'1x': 1}}, 'not a valid ROS parameter name')],
)
def test_unwritable_metadata_is_refused_clearly(metadata, message):
    with pytest.raises(CalibrationFileError, match=message):
        calibration_yaml(Calibration(np.zeros(3), np.eye(3), 1.0, 'full', metadata))


@pytest.mark.parametrize('name', ['', 'two words', '1abc', 'a/'])
def test_bad_node_names_are_refused(tmp_path, name):
    with pytest.raises(CalibrationFileError, match='node name'):
        save_calibration(tmp_path / 'c.yaml', fitted_calibration(), node_name=name)


def test_another_node_name(tmp_path):
    path = tmp_path / 'c.yaml'
    save_calibration(path, fitted_calibration(), node_name='left_compass')
    assert 'left_compass' in yaml.safe_load(path.read_text())
    assert load_calibration(path, node_name='left_compass').field_strength == 4.9e-5
    with pytest.raises(CalibrationFileError, match="no 'mag_calibrator' section"):
        load_calibration(path)


# -- atomic save ----------------------------------------------------------------------------------


def test_directories_are_created(tmp_path):
    path = tmp_path / 'a' / 'b' / 'calibration.yaml'
    save_calibration(path, fitted_calibration())
    assert load_calibration(path).model == 'full'


def test_the_old_file_survives_a_write_that_fails_midway(tmp_path, monkeypatch):
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, fitted_calibration(samples=1))
    before = path.read_bytes()
    real_write = os.write

    def write_half_then_fail(descriptor, data):
        real_write(descriptor, bytes(data[: len(data) // 2]))
        raise OSError(28, 'No space left on device')

    with monkeypatch.context() as patch:
        patch.setattr(os, 'write', write_half_then_fail)
        with pytest.raises(CalibrationFileError, match='No space left on device') as error:
            save_calibration(path, fitted_calibration(samples=2))
    assert str(path) in str(error.value)
    assert path.read_bytes() == before
    assert load_calibration(path).metadata['samples'] == 1
    assert sorted(os.listdir(tmp_path)) == ['calibration.yaml']  # no temporary left behind


@pytest.mark.parametrize('failing', ['fsync', 'replace'])
def test_the_old_file_survives_a_failed_flush_or_rename(tmp_path, monkeypatch, failing):
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, fitted_calibration(samples=1))
    before = path.read_bytes()

    def fail(*args):
        raise OSError(5, 'Input/output error')

    with monkeypatch.context() as patch:
        patch.setattr(os, failing, fail)
        with pytest.raises(CalibrationFileError, match='Input/output error'):
            save_calibration(path, fitted_calibration(samples=2))
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ['calibration.yaml']


def test_save_flushes_file_and_directory(tmp_path, monkeypatch):
    flushed = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, 'fsync', lambda fd: (flushed.append(fd), real_fsync(fd)))
    save_calibration(tmp_path / 'calibration.yaml', fitted_calibration())
    assert len(flushed) == 2  # the temporary file, then the directory after the rename


def test_save_keeps_permissions_and_follows_symlinks(tmp_path):
    real = tmp_path / 'real.yaml'
    save_calibration(real, fitted_calibration(samples=1))
    os.chmod(real, 0o600)
    link = tmp_path / 'link.yaml'
    link.symlink_to(real)
    save_calibration(link, fitted_calibration(samples=2))
    assert link.is_symlink()
    assert load_calibration(real).metadata['samples'] == 2
    assert real.stat().st_mode & 0o777 == 0o600


def test_saving_onto_a_directory_gives_a_clear_error_and_leaves_no_litter(tmp_path):
    target = tmp_path / 'taken'
    target.mkdir()
    with pytest.raises(CalibrationFileError, match='cannot write') as error:
        save_calibration(target, fitted_calibration())
    assert str(target) in str(error.value)
    assert sorted(os.listdir(tmp_path)) == ['taken'] and target.is_dir()


def test_an_unwritable_place_gives_a_clear_error(tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    with pytest.raises(CalibrationFileError, match='cannot write'):
        save_calibration(blocker / 'calibration.yaml', fitted_calibration())


# -- validated load -------------------------------------------------------------------------------

GOOD = """mag_calibrator:
  ros__parameters:
    calibration:
      offset: [1.0, 2.0, 3.0]
      matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
      field_strength: 50.0
      model: "full"
"""


@pytest.mark.parametrize(
    ('content', 'message'),
    [
        ('', 'the file is empty'),
        ('mag_calibrator: [\n', r'not valid YAML at line \d+'),
        ('mag_calibrator:\n  ros__parameters:\n\tcalibration: 1\n', 'not valid YAML'),
        ('- a\n- b\n', 'expected a mapping'),
        ('just text\n', 'expected a mapping'),
        ('other_node:\n  ros__parameters: {}\n', "no 'mag_calibrator' section"),
        ('mag_calibrator:\n  parameters: {}\n', 'no ros__parameters'),
        ('mag_calibrator:\n  ros__parameters:\n    rate: 1.0\n', 'no calibration parameters'),
        (GOOD.replace('      matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n', ''),
         'missing calibration.matrix'),
        (GOOD.replace('[1.0, 2.0, 3.0]', '[1.0, 2.0]'), 'offset must have 3 numbers, got 2'),
        (GOOD.replace('[1.0, 2.0, 3.0]', '1.0'), 'offset must be a list of 3 numbers'),
        (GOOD.replace('[1.0, 2.0, 3.0]', '[1.0, "two", 3.0]'), 'offset must contain numbers'),
        (GOOD.replace('[1.0, 2.0, 3.0]', '[1.0, true, 3.0]'), 'offset must contain numbers'),
        (GOOD.replace('0.0, 0.0, 1.0]', '0.0, 1.0]'), 'matrix must have 9 numbers, got 8'),
        (GOOD.replace('0.0, 0.0, 1.0]', '0.0, 0.0, .nan]'), 'matrix has non-finite values'),
        (GOOD.replace('[1.0, 2.0, 3.0]', '[1.0, .inf, 3.0]'), 'offset has non-finite values'),
        (GOOD.replace('0.0, 0.0, 1.0]', '0.0, 0.0, -1.0]'), 'not positive definite'),
        (GOOD.replace('50.0', '-50.0'), 'field_strength must be a positive finite number'),
        (GOOD.replace('50.0', '"strong"'), 'field_strength must be a number'),
        (GOOD.replace('"full"', '"banana"'), 'model must be one of'),
    ],
)
def test_every_kind_of_corrupt_file_is_named(tmp_path, content, message):
    path = tmp_path / 'broken.yaml'
    path.write_text(content)
    with pytest.raises(CalibrationFileError, match=message) as error:
        load_calibration(path)
    assert str(error.value).startswith(f'{path}: ')


def test_binary_garbage_is_not_a_text_file(tmp_path):
    path = tmp_path / 'garbage.yaml'
    path.write_bytes(bytes(range(128, 256)) * 4)
    with pytest.raises(CalibrationFileError, match='not a text'):
        load_calibration(path)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(CalibrationFileError, match='no such file') as error:
        load_calibration(tmp_path / 'nowhere.yaml')
    assert 'nowhere.yaml' in str(error.value)
    with pytest.raises(CalibrationFileError, match='is a directory'):
        load_calibration(tmp_path)


def test_load_accepts_what_ros_accepts(tmp_path):
    """Hand-written files: dotted names, the /** wildcard, integers, no model."""
    path = tmp_path / 'hand.yaml'
    path.write_text(
        '/**:\n  ros__parameters:\n    calibration.offset: [1, 2, 3]\n'
        '    calibration.matrix: [2, 0, 0, 0, 2, 0, 0, 0, 2]\n'
        '    calibration:\n      field_strength: 50\n      note: "by hand"\n'
    )
    calibration = load_calibration(path)
    np.testing.assert_array_equal(calibration.offset, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(calibration.matrix, 2.0 * np.eye(3))
    assert calibration.model == 'full' and calibration.metadata == {'note': 'by hand'}


# -- parameters -----------------------------------------------------------------------------------


def test_calibration_from_parameters_takes_ros_arrays():
    import array

    calibration = calibration_from_parameters(
        array.array('d', [1.0, 2.0, 3.0]), array.array('d', SOFT_IRON.reshape(9)), 50.0, 'full',
        {'samples': 3},
    )
    np.testing.assert_array_equal(calibration.matrix, SOFT_IRON)
    assert calibration.metadata == {'samples': 3}
    nested = calibration_from_parameters([1, 2, 3], SOFT_IRON.tolist(), 50, 'axis')
    np.testing.assert_array_equal(nested.matrix, SOFT_IRON)


def test_calibration_from_parameters_names_every_problem():
    with pytest.raises(CalibrationError) as error:
        calibration_from_parameters([1.0, 2.0], [1.0] * 8, True, 'magic')
    message = str(error.value)
    for part in ('offset must have 3', 'matrix must have 9', 'field_strength must be a number',
                 'model must be one of'):
        assert part in message


# -- rclpy --params-file --------------------------------------------------------------------------


def test_rclpy_loads_the_file_as_a_params_file(tmp_path):
    """rcl's own YAML parser must type every value as the node declares it."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    calibration = Calibration(  # integral values: the int-vs-double trap
        np.array([1.0, -2.0, 0.0]), np.diag([2.0, 1.0, 1.0]), 50.0, 'full',
        {**METADATA, 'frame_id': 'on', 'condition_number': 1.0},
    )
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, calibration)
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context)
    try:
        node = Node('mag_calibrator', context=context)
        try:
            declared = {
                'offset': Parameter.Type.DOUBLE_ARRAY,
                'matrix': Parameter.Type.DOUBLE_ARRAY,
                'field_strength': Parameter.Type.DOUBLE,
                'model': Parameter.Type.STRING,
                'samples': Parameter.Type.INTEGER,
                'time': Parameter.Type.STRING,
                'frame_id': Parameter.Type.STRING,
                'condition_number': Parameter.Type.DOUBLE,
            }
            values = {
                key: node.declare_parameter(f'calibration.{key}', kind).value
                for key, kind in declared.items()
            }
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    assert values['frame_id'] == 'on' and values['samples'] == 100
    rebuilt = calibration_from_parameters(
        values['offset'], values['matrix'], values['field_strength'], values['model']
    )
    np.testing.assert_array_equal(rebuilt.offset, calibration.offset)
    np.testing.assert_array_equal(rebuilt.matrix, calibration.matrix)
    assert rebuilt.field_strength == 50.0


def test_module_never_imports_rclpy():
    source = open(calibration_file.__file__, encoding='utf-8').read()
    assert not re.search(r'^\s*(import|from)\s+rclpy', source, flags=re.M)
