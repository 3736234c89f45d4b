# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibration file: ROS 2 parameters YAML, exact round trip, atomic save, validated load."""

import array
import os
import re
import stat
import subprocess
import sys
import threading
import time

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
import yaml

from mag_calibrator_ros.calibration.fit.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.store import calibration_file, params_yaml, safe_file
from mag_calibrator_ros.calibration.store.calibration_file import (
    MAX_FILE_BYTES,
    MAX_NODES,
    CalibrationFileError,
    CalibrationFileMissingError,
    calibration_from_parameters,
    calibration_yaml,
    default_calibration_path,
    default_load_path,
    load_calibration,
    read_calibration_file,
    resolve_calibration_path,
    save_calibration,
    section_matches,
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
    loaded = read_calibration_file(path, node_name='left_compass')
    assert loaded.calibration.field_strength == 4.9e-5 and loaded.notes == ()
    other = read_calibration_file(path)  # the file's only calibration, with a note
    assert other.sections == ('left_compass',)
    assert "used section 'left_compass', written for another node" in other.notes[0]


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
    with pytest.raises(CalibrationFileError, match='is a directory') as error:
        save_calibration(target, fitted_calibration())
    assert str(target) in str(error.value)
    assert sorted(os.listdir(tmp_path)) == ['taken'] and target.is_dir()


def test_an_unwritable_place_gives_a_clear_error(tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    with pytest.raises(CalibrationFileError, match='cannot write'):
        save_calibration(blocker / 'calibration.yaml', fitted_calibration())


# -- saving only where it belongs (issue 9) -------------------------------------------------------


@pytest.mark.parametrize('device', ['/dev/full', '/dev/null'])
def test_save_never_replaces_a_device(tmp_path, device, never_written):
    """As root, ``calibration_file:=/dev/full`` + save turned the device into a regular file."""
    link = tmp_path / 'link.yaml'
    link.symlink_to(device)
    for path in (device, link):
        with pytest.raises(CalibrationFileError, match='is a character device.*only a regular'):
            save_calibration(path, fitted_calibration())
    assert stat.S_ISCHR(os.stat(device).st_mode)


def test_save_never_writes_through_a_fifo(tmp_path, never_written):
    fifo = tmp_path / 'fifo.yaml'
    os.mkfifo(fifo)
    with pytest.raises(CalibrationFileError, match=f'{fifo}: is a FIFO'):
        save_calibration(fifo, fitted_calibration())
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_save_and_load_resolve_a_path_the_same_way(tmp_path, monkeypatch):
    """Save used to apply '..' past a missing directory and write where load did not look."""
    name = str(tmp_path / 'missing' / '..' / 'c.yaml')
    written = save_calibration(name, fitted_calibration())
    assert written == resolve_calibration_path(name) == tmp_path / 'c.yaml'
    loaded = read_calibration_file(name)
    assert loaded.path == written and loaded.calibration.field_strength == 4.9e-5
    monkeypatch.setenv('HOME', str(tmp_path))
    assert save_calibration('~/d.yaml', fitted_calibration()) == tmp_path / 'd.yaml'
    assert read_calibration_file('~/d.yaml').path == tmp_path / 'd.yaml'


def test_save_writes_only_what_load_accepts(tmp_path):
    path = tmp_path / 'c.yaml'
    save_calibration(path, fitted_calibration(samples=1))
    before = path.read_bytes()
    for metadata in ({'notes': 'x' * MAX_FILE_BYTES}, {'many': list(range(MAX_NODES + 1))},
                     {'deep': _nested_dict(20)}):
        with pytest.raises(CalibrationFileError, match=f'{path}: cannot save: '):
            save_calibration(path, fitted_calibration(**metadata))
    assert path.read_bytes() == before


def _nested_dict(depth):
    tree = {'leaf': 1.0}
    for _ in range(depth):
        tree = {'level': tree}
    return tree


def test_interrupted_saves_leave_no_temporary_for_good(tmp_path):
    """400 kill -9 during ~/save left 3 temporaries behind for good; the next save removes them."""
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, fitted_calibration(samples=1))
    dead = subprocess.run([sys.executable, '-c', 'import os; print(os.getpid())'],
                          capture_output=True, text=True, check=True).stdout.strip()
    stale = [tmp_path / f'.calibration.yaml.{dead}.k2j4h5g6.tmp',  # a killed writer
             tmp_path / '.calibration.yaml.ab3kz9_q.tmp']  # a killed writer of older versions
    for leftover in stale:
        leftover.write_text('mag_calibrator:\n  ros__')
        os.utime(leftover, (time.time() - 120, time.time() - 120))
    save_calibration(path, fitted_calibration(samples=2))
    assert sorted(os.listdir(tmp_path)) == ['calibration.yaml']
    assert load_calibration(path).metadata['samples'] == 2


def test_saves_and_loads_from_many_threads_always_see_a_whole_file(tmp_path):
    """What a node running load/save on a worker thread relies on: no shared state, atomic."""
    path = tmp_path / 'c.yaml'
    save_calibration(path, fitted_calibration(samples=0))
    problems = []

    def work(worker):
        for step in range(15):
            try:
                if worker % 2:
                    save_calibration(path, fitted_calibration(samples=worker * 100 + step))
                else:
                    assert load_calibration(path).field_strength == 4.9e-5
            except Exception as error:  # noqa: BLE001 - collected and reported below
                problems.append(repr(error))

    threads = [threading.Thread(target=work, args=(worker,)) for worker in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert problems == []
    assert sorted(os.listdir(tmp_path)) == ['c.yaml']


# -- validated load -------------------------------------------------------------------------------

OFFSET_TEXT = '[1.0e-05, 2.0e-05, 3.0e-05]'
"""GOOD's offset as written (tesla, as every calibration file is)."""
GOOD = """mag_calibrator:
  ros__parameters:
    calibration:
      offset: [1.0e-05, 2.0e-05, 3.0e-05]
      matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
      field_strength: 5.0e-05
      model: "full"
"""

BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + ''.join(
    f'{chr(98 + i)}: &{chr(98 + i)} [' + ','.join([f'*{chr(97 + i)}'] * 9) + ']\n'
    for i in range(8)
)
WITH_METADATA = GOOD + '      {}\n'


@pytest.mark.parametrize(
    ('content', 'message'),
    [
        ('', 'the file is empty'),
        ('mag_calibrator: [\n', r'not valid YAML at line \d+'),
        ('mag_calibrator:\n  ros__parameters:\n\tcalibration: 1\n', 'not valid YAML'),
        ('- a\n- b\n', 'expected a mapping'),
        ('just text\n', 'expected a mapping'),
        ('other_node:\n  ros__parameters: {}\n',
         "no calibration parameters for /mag_calibrator .sections 'other_node'"),
        ('mag_calibrator:\n  parameters: {}\n', 'no ros__parameters'),
        ('mag_calibrator:\n  ros__parameters:\n    rate: 1.0\n', 'no calibration parameters'),
        (GOOD.replace('      matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n', ''),
         'missing calibration.matrix'),
        (GOOD.replace(OFFSET_TEXT, '[1.0, 2.0]'), 'offset must have 3 numbers, got 2'),
        (GOOD.replace(OFFSET_TEXT, '1.0'), 'offset must be a list of 3 numbers'),
        (GOOD.replace(OFFSET_TEXT, '[1.0, "two", 3.0]'), 'offset must contain numbers'),
        (GOOD.replace(OFFSET_TEXT, '[1.0, true, 3.0]'), 'offset must contain numbers'),
        (GOOD.replace('0.0, 0.0, 1.0]', '0.0, 1.0]'), 'matrix must have 9 numbers, got 8'),
        (GOOD.replace('0.0, 0.0, 1.0]', '0.0, 0.0, .nan]'), 'matrix has non-finite values'),
        (GOOD.replace(OFFSET_TEXT, '[1.0, .inf, 3.0]'), 'offset has non-finite values'),
        (GOOD.replace('0.0, 0.0, 1.0]', '0.0, 0.0, -1.0]'), 'not positive definite'),
        (GOOD.replace('5.0e-05', '-5.0e-05'), 'field_strength must be a positive finite number'),
        (GOOD.replace('5.0e-05', '"strong"'), 'field_strength must be a number'),
        (GOOD.replace('"full"', '"banana"'), 'model must be one of'),
        pytest.param(WITH_METADATA.format('n: ' + '1' * 5000).replace(
            OFFSET_TEXT, '[' + '9' * 5000 + ', 2.0, 3.0]'),
            "offset must contain numbers only, got '99999", id='5000-digit integer'),
        pytest.param('mag_calibrator: &x\n  ros__parameters: *x\n', 'anchors and aliases',
                     id='self-referencing alias'),
        pytest.param(BILLION_LAUGHS, 'anchors and aliases', id='billion laughs'),
        pytest.param('mag_calibrator: ' + '[' * 5000 + ']' * 5000, 'nested deeper than',
                     id='5000-deep nesting'),
        pytest.param('mag_calibrator:\n  ros__parameters:\n    calibration:\n      offset: ['
                     + ', '.join(['1.0'] * 5000) + ']\n', f'more than {MAX_NODES} values',
                     id='100 MB list file, in small'),
        pytest.param(WITH_METADATA.format('time: !!timestamp 2026-13-45'), 'explicit YAML tags',
                     id='tagged date'),
        pytest.param('mag_calibrator:\n  ros__parameters: 5\n', 'no ros__parameters',
                     id='parameters a number'),
        pytest.param('mag_calibrator:\n  ros__parameters:\n    calibration: [1, 2]\n',
                     'calibration must be a mapping of parameters', id='calibration a list'),
        pytest.param(GOOD.replace(OFFSET_TEXT, '"oops"'),
                     "offset must be a list of 3 numbers, got 'oops'", id='offset a string'),
        pytest.param(GOOD.replace(OFFSET_TEXT, '{x: 1}'),
                     'offset must be a list of 3 numbers', id='offset a mapping'),
        pytest.param(GOOD.replace('"full"', '[1]'), 'model must be one of', id='model a list'),
        pytest.param('1: {ros__parameters: {}}\n', 'top key 1 is not a valid node name',
                     id='top key a number'),
        pytest.param('"/robot*/x": {ros__parameters: {}}\n', 'params-file would refuse',
                     id='top key with a partial wildcard'),
        pytest.param('? ' + '/**' * 3000 + '/x\n: {ros__parameters: {}}\n',
                     'no calibration parameters', id='3000 ** wildcards'),  # recursion, once
    ],
)
def test_every_kind_of_corrupt_file_is_named(tmp_path, content, message):
    path = tmp_path / 'broken.yaml'
    path.write_text(content)
    with pytest.raises(CalibrationFileError, match=message) as error:
        load_calibration(path)
    assert str(error.value).startswith(f'{path}: ')
    assert len(str(error.value)) < 400  # one readable line, whatever the file held


def test_binary_garbage_is_not_a_text_file(tmp_path):
    path = tmp_path / 'garbage.yaml'
    path.write_bytes(bytes(range(128, 256)) * 4)
    with pytest.raises(CalibrationFileError, match='not a text'):
        load_calibration(path)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(CalibrationFileMissingError, match='no such file') as error:
        load_calibration(tmp_path / 'nowhere.yaml')
    assert 'nowhere.yaml' in str(error.value)
    assert isinstance(error.value, CalibrationFileError)  # one except clause catches both
    (tmp_path / 'dir').mkdir()
    with pytest.raises(CalibrationFileError) as error:
        load_calibration(tmp_path / 'dir' / '..' / 'dir')
    assert not isinstance(error.value, CalibrationFileMissingError)
    with pytest.raises(CalibrationFileError, match='is a directory'):
        load_calibration(tmp_path)


def test_load_accepts_what_ros_accepts(tmp_path):
    """Hand-written files: dotted names, the /** wildcard, integers, no model."""
    path = tmp_path / 'hand.yaml'
    path.write_text(
        '/**:\n  ros__parameters:\n    calibration.offset: [0, 0, 1.0e-5]\n'
        '    calibration.matrix: [2, 0, 0, 0, 2, 0, 0, 0, 2]\n'
        '    calibration:\n      field_strength: 5.0e-5\n      note: "by hand"\n'
    )
    calibration = load_calibration(path)
    np.testing.assert_array_equal(calibration.offset, [0.0, 0.0, 1e-5])
    np.testing.assert_array_equal(calibration.matrix, 2.0 * np.eye(3))
    assert calibration.model == 'full' and calibration.metadata == {'note': 'by hand'}


# -- hostile files: every failure a CalibrationFileError naming file and problem (issue 9) --------



@pytest.mark.parametrize(
    ('name', 'message'),
    [
        ('/dev/zero', '/dev/zero: is a character device'),
        ('/dev/null', '/dev/null: is a character device'),
        ('x' * 300 + '/c.yaml', 'File name too long'),
        ('', 'empty'),
        ('a\0b', 'NUL'),
    ],
)
def test_unreadable_places_are_refused_clearly(tmp_path, monkeypatch, name, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(CalibrationFileError, match=message):
        load_calibration(name)


def test_a_fifo_is_refused_at_once_and_a_huge_file_before_reading(tmp_path, monkeypatch):
    fifo = tmp_path / 'fifo.yaml'
    os.mkfifo(fifo)
    blocked = threading.Timer(60.0, lambda: os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)))
    blocked.start()  # frees a blocking open, so a regression fails instead of hanging
    try:
        with pytest.raises(CalibrationFileError, match='is a FIFO'):
            load_calibration(fifo)
    finally:
        blocked.cancel()
    huge = tmp_path / 'huge.yaml'
    with open(huge, 'wb') as file:
        file.truncate(100_000_000)
    monkeypatch.setattr(os, 'read', lambda *args: pytest.fail('read a file over the limit'))
    with pytest.raises(CalibrationFileError, match=f'too large .*limit is {MAX_FILE_BYTES}'):
        load_calibration(huge)


def test_permission_denied_is_named(tmp_path, monkeypatch):
    path = tmp_path / 'c.yaml'
    save_calibration(path, fitted_calibration())

    def deny(*args, **kwargs):
        raise PermissionError(13, 'Permission denied')

    monkeypatch.setattr(os, 'open', deny)  # tests may run as root, who reads anything
    with pytest.raises(CalibrationFileError, match='cannot read: Permission denied'):
        load_calibration(path)


def test_dates_and_huge_numbers_in_metadata_load_as_rcl_reads_them(tmp_path):
    """``time: 2026-13-45`` and a 5,000-digit integer crashed the node (ValueError)."""
    path = tmp_path / 'c.yaml'
    path.write_text(WITH_METADATA.format('time: 2026-13-45') + '      day: 2026-01-01\n'
                    '      big: ' + '1' * 5000 + '\n      large: 123456789012345678901234\n')
    loaded = load_calibration(path)
    assert loaded.metadata['time'] == '2026-13-45' and loaded.metadata['day'] == '2026-01-01'
    assert loaded.metadata['big'] == '1' * 5000  # rcl: a string (beyond a double)
    assert loaded.metadata['large'] == 1.2345678901234568e23  # rcl: a double (beyond int64)
    save_calibration(path, loaded)
    assert load_calibration(path).metadata == loaded.metadata


@settings(max_examples=300)
@given(content=st.one_of(
    st.binary(max_size=600),
    st.text(alphabet='mag_calibrator/*:ros__parameters offset[]{}&!.-0123456789e"\n ',
            max_size=400),
    st.builds(lambda value: GOOD.replace(OFFSET_TEXT, value),
              st.text(alphabet='[]{}-,.0123456789eE"naif ', max_size=40)),
))
def test_any_file_loads_or_raises_calibration_file_error(tmp_path_factory, content):
    path = tmp_path_factory.mktemp('fuzz') / 'c.yaml'
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    try:
        loaded = load_calibration(path)
    except CalibrationFileError as error:
        assert str(error).startswith(f'{path}: ')
        return
    save_calibration(path, loaded)  # whatever loads also saves


# -- parameters -----------------------------------------------------------------------------------


def test_calibration_from_parameters_takes_ros_arrays():
    calibration = calibration_from_parameters(
        array.array('d', [1e-5, 2e-5, 3e-5]), array.array('d', SOFT_IRON.reshape(9)), 5e-5,
        'full', {'samples': 3},
    )
    np.testing.assert_array_equal(calibration.matrix, SOFT_IRON)
    assert calibration.metadata == {'samples': 3}
    nested = calibration_from_parameters([0, 0, 0], SOFT_IRON.tolist(), 5e-5, 'axis')
    np.testing.assert_array_equal(nested.matrix, SOFT_IRON)


def test_calibration_from_parameters_names_every_problem():
    with pytest.raises(CalibrationError) as error:
        calibration_from_parameters([1.0, 2.0], [1.0] * 8, True, 'magic')
    message = str(error.value)
    for part in ('offset must have 3', 'matrix must have 9', 'field_strength must be a number',
                 'model must be one of'):
        assert part in message


@pytest.mark.parametrize(
    ('offset', 'matrix', 'strength'),
    [([0, 0, 0], [1, 0, 0, 0, 1, 0, 0, 0, 1], 5e-5),  # a hand-written --params-file: integers
     (np.array([0, 0, 0]), np.eye(3, dtype=int), np.float32(5e-5)),
     (array.array('q', [0, 0, 0]), array.array('q', [1, 0, 0, 0, 1, 0, 0, 0, 1]), 5e-5)],
)
def test_integers_stand_for_doubles(offset, matrix, strength):
    """Integers stand for doubles (a field strength in tesla is never one: see
    test_numbers_that_cannot_be_tesla_are_refused_naming_the_unit)."""
    calibration = calibration_from_parameters(offset, matrix, strength)
    assert calibration.offset.dtype == float
    assert calibration.field_strength == pytest.approx(5e-5)
    np.testing.assert_array_equal(calibration.matrix, np.eye(3))


@pytest.mark.parametrize(('offset', 'strength', 'words'), [
    ([120.03, -80.0, 60.0], 50.0, 'looks like µT'),                  # the unit every log shows
    ([0.0, 0.0, 0.0], 1.0, 'a normalised calibration'),
    ([0.0, 0.0, 0.0], 0.49, 'looks like gauss'),
    ([0.0, 0.0, 0.0], 5e-11, 'far below'),
    ([0.3, 0.0, 0.0], 5e-5, 'offset 0.3 T is beyond'),
])
def test_numbers_that_cannot_be_tesla_are_refused_naming_the_unit(tmp_path, offset, strength,
                                                                  words):
    """A hand-edited file with the offset in µT loaded as tesla and published |B| of 1.9e8 µT
    (issue #46): every entry reads through calibration_from_parameters, which refuses it."""
    with pytest.raises(CalibrationError, match=words):
        calibration_from_parameters(offset, np.eye(3).reshape(9), strength)
    path = tmp_path / 'c.yaml'
    path.write_text(GOOD.replace(OFFSET_TEXT, str(offset)).replace(
        '5.0e-05', repr(strength)))
    with pytest.raises(CalibrationFileError, match=words):
        load_calibration(path)


@pytest.mark.parametrize(
    ('kwargs', 'message'),
    [({'offset': 'oops'}, "offset must be a list of 3 numbers, got 'oops'"),
     ({'offset': b'abc'}, 'offset must be a list of 3 numbers'),
     ({'offset': None}, 'offset must be a list of 3 numbers, got None'),
     ({'offset': {'x': 1}}, 'offset must be a list of 3 numbers'),
     ({'offset': [1, 2, 10**400]}, 'offset is out of range'),
     ({'matrix': np.zeros(10**6)}, 'matrix must have 9 numbers, got 1000000'),
     ({'matrix': [[1, 0, 0], [0, 1]]}, 'matrix must have 9 numbers, got 5'),
     ({'field_strength': '50'}, "field_strength must be a number, got '50'"),
     ({'field_strength': 10**400}, 'field_strength is out of range'),
     ({'field_strength': np.complex128(1)}, 'field_strength must be a number'),
     ({'model': None}, 'model must be one of'),
     ({'metadata': {'rotation': [1, 0, 0, 0, 1, 0, 0, 0, -1]}}, 'a reflection, not a rotation'),
     ({'metadata': {'rotation': [1, 0.1, 0, 0, 1, 0, 0, 0, 1]}}, 'rotation is not orthonormal'),
     ({'metadata': {'rotation': 'identity'}}, 'rotation must be a list of 9 numbers'),
     ({'metadata': ['samples', 3]}, 'metadata must be a mapping')],
)
def test_wrong_parameter_types_are_a_calibration_error(kwargs, message):
    arguments = {'offset': [0.0, 0.0, 0.0], 'matrix': np.eye(3).reshape(9),
                 'field_strength': 5e-5, **kwargs}
    with pytest.raises(CalibrationError, match=message) as error:
        calibration_from_parameters(**arguments)
    assert len(str(error.value)) < 300


# -- metadata keys (issue 9) ----------------------------------------------------------------------


def test_metadata_keys_ros_cannot_hold_are_dropped_on_load_so_every_save_works(tmp_path):
    """Keys like 'bad key' loaded, then made every later ~/save fail."""
    path = tmp_path / 'c.yaml'
    path.write_text(WITH_METADATA.format('"bad key": 1') + '      "1x": 2\n      ok: 3\n'
                    '      7: 4\n      "ключ": 5\n      nested: {"a b": 6, fine: 7}\n')
    loaded = read_calibration_file(path)
    assert loaded.calibration.metadata == {'ok': 3, 'nested': {'fine': 7}}
    (note,) = loaded.notes
    for name in ('calibration.bad key', 'calibration.1x', 'calibration.7', 'calibration.ключ',
                 'calibration.nested.a b'):
        assert name in note
    save_calibration(path, loaded.calibration)
    assert load_calibration(path).metadata == {'ok': 3, 'nested': {'fine': 7}}


def test_dotted_and_nested_names_that_clash_are_dropped_with_a_note(tmp_path):
    path = tmp_path / 'c.yaml'
    path.write_text(WITH_METADATA.format('a: 1') + '      a.b: 2\n')
    loaded = read_calibration_file(path)
    assert loaded.calibration.metadata == {'a': 1}
    assert 'calibration.a.b' in loaded.notes[0]


# -- calibration.rotation -------------------------------------------------------------------------

ROTATION_45 = [0.7071, -0.7071, 0.0, 0.7071, 0.7071, 0.0, 0.0, 0.0, 1.0]  # 4 decimals, by hand


def test_rotation_is_optional_validated_and_round_trips_as_doubles(tmp_path):
    path = tmp_path / 'c.yaml'
    path.write_text(WITH_METADATA.format(f'rotation: {ROTATION_45}'))
    loaded = load_calibration(path)
    assert loaded.rotation.reshape(9).tolist() == ROTATION_45  # a field, not metadata
    assert 'rotation' not in loaded.metadata
    save_calibration(path, loaded.with_rotation([1, 0, 0, 0, 1, 0, 0, 0, 1]))
    section = yaml.safe_load(path.read_text())['mag_calibrator']['ros__parameters']['calibration']
    assert list(section)[:3] == ['offset', 'matrix', 'rotation']
    assert all(type(value) is float for value in section['rotation'])  # never an int array
    path.write_text(GOOD)
    np.testing.assert_array_equal(load_calibration(path).rotation, np.eye(3))  # absent: identity


def test_the_rotation_round_trips_and_is_applied(tmp_path):
    """corrected = R M (raw - b), saved and loaded with and without R."""
    path = tmp_path / 'c.yaml'
    rotation = np.array(ROTATION_45).reshape(3, 3)
    rotation = np.linalg.svd(rotation)[0] @ np.linalg.svd(rotation)[2]  # exactly orthonormal
    plain = fitted_calibration()
    rotated = plain.with_rotation(rotation, alignment_angle_deg=45.0)
    raw = np.array([[3e-5, -1e-5, 2e-5], [-4e-5, 2e-5, 1e-5]])
    np.testing.assert_allclose(rotated.apply(raw), plain.apply(raw) @ rotation.T)
    np.testing.assert_allclose(rotated.correction, rotation @ plain.matrix)
    for calibration in (plain, rotated):
        save_calibration(path, calibration)
        loaded = load_calibration(path)
        np.testing.assert_array_equal(loaded.rotation, calibration.rotation)
        np.testing.assert_allclose(loaded.apply(raw), calibration.apply(raw), rtol=1e-15)
        assert loaded.aligned == calibration.aligned
        assert loaded.scaled(1e6).rotation is not None
        np.testing.assert_array_equal(loaded.scaled(1e6).rotation, calibration.rotation)
    assert load_calibration(path).metadata['alignment_angle_deg'] == 45.0


def test_rotation_in_metadata_is_refused_not_ignored():
    with pytest.raises(CalibrationError, match='field of the calibration, not metadata'):
        fitted_calibration(rotation=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    ('rotation', 'message'),
    [('[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]', 'a reflection'),
     ('[2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]', 'not orthonormal'),
     ('[1.0, 0.0, 0.0]', 'rotation must have 9 numbers, got 3'),
     ('[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, .nan]', 'rotation has non-finite values'),
     ('"identity"', 'rotation must be a list of 9 numbers')],
)
def test_a_wrong_rotation_is_refused(tmp_path, rotation, message):
    path = tmp_path / 'c.yaml'
    path.write_text(WITH_METADATA.format(f'rotation: {rotation}'))
    with pytest.raises(CalibrationFileError, match=message):
        load_calibration(path)
    with pytest.raises(CalibrationError, match=message):
        fitted_calibration().with_rotation(yaml.safe_load(rotation))


# -- one file per node; sections (issue 10) -------------------------------------------------------


@pytest.mark.parametrize(
    ('node', 'file_name'),
    [('/robot1/mag_calibrator', 'robot1__mag_calibrator.yaml'),
     ('/mag_calibrator', 'mag_calibrator.yaml'),
     ('mag_calibrator', 'mag_calibrator.yaml'),
     ('/fleet/robot2/left_compass', 'fleet__robot2__left_compass.yaml')],
)
def test_default_calibration_path_is_per_node(monkeypatch, tmp_path, node, file_name):
    monkeypatch.delenv('ROS_HOME', raising=False)
    monkeypatch.setenv('HOME', str(tmp_path))
    assert default_calibration_path(node) == tmp_path / '.ros' / 'mag_calibrator' / file_name
    monkeypatch.setenv('ROS_HOME', str(tmp_path / 'ros_home'))
    assert default_calibration_path(node) == tmp_path / 'ros_home' / 'mag_calibrator' / file_name


@pytest.mark.parametrize('node', ['', '/', '/robot1/', '/1robot/x', '/a b/x', '/**', None])
def test_default_calibration_path_refuses_non_names(node):
    with pytest.raises(CalibrationFileError, match='not a valid node name'):
        default_calibration_path(node)


def test_the_old_shared_default_is_read_only_by_the_root_namespace_node(monkeypatch, tmp_path):
    monkeypatch.delenv('ROS_HOME', raising=False)
    monkeypatch.setenv('HOME', str(tmp_path))
    legacy = tmp_path / '.ros' / 'mag_calibrator' / 'calibration.yaml'
    assert default_load_path('/mag_calibrator') == default_calibration_path('/mag_calibrator')
    save_calibration(legacy, fitted_calibration())
    assert default_load_path('/mag_calibrator') == legacy
    assert default_load_path('/robot1/mag_calibrator') == default_calibration_path(
        '/robot1/mag_calibrator')  # never another robot's calibration
    assert default_load_path('/left_compass') == default_calibration_path('/left_compass')
    save_calibration(default_calibration_path('/mag_calibrator'), fitted_calibration())
    assert default_load_path('/mag_calibrator') == default_calibration_path('/mag_calibrator')


# what rcl (Jazzy) applies to which node: measured with rclpy, checked again on every run
# (test_calibration_file_rclpy.py)
RCL_MATCHES = {
    'mag_calibrator': {'/mag_calibrator'},
    '/mag_calibrator': {'/mag_calibrator'},
    '/robot1/mag_calibrator': {'/robot1/mag_calibrator'},
    'robot1/mag_calibrator': {'/robot1/mag_calibrator'},
    '/**': {'/mag_calibrator', '/robot1/mag_calibrator', '/robot1/sub/mag_calibrator'},
    '/**/mag_calibrator': {'/mag_calibrator', '/robot1/mag_calibrator',
                           '/robot1/sub/mag_calibrator'},
    '/*/mag_calibrator': {'/robot1/mag_calibrator'},
    '/robot1/*': {'/robot1/mag_calibrator'},
    '/robot1/**': {'/robot1/mag_calibrator', '/robot1/sub/mag_calibrator'},
    '/robot1/**/mag_calibrator': {'/robot1/mag_calibrator', '/robot1/sub/mag_calibrator'},
    '/*': {'/mag_calibrator'},
    '/robot2/mag_calibrator': set(),
}
NODES = ('/mag_calibrator', '/robot1/mag_calibrator', '/robot1/sub/mag_calibrator')


@pytest.mark.parametrize('key', list(RCL_MATCHES))
def test_section_matching_follows_rcl(key):
    assert {node for node in NODES if section_matches(key, node)} == RCL_MATCHES[key]


@pytest.mark.parametrize('key', ['mag_calibrator', '/**', '/robot1/mag_calibrator',
                                 '/**/mag_calibrator', '/robot2/mag_calibrator'])
def test_every_key_style_loads(tmp_path, key):
    """Old files (mag_calibrator:), wildcards, fully qualified names, another robot's file."""
    path = tmp_path / 'c.yaml'
    save_calibration(path, fitted_calibration(), node_name=key)
    loaded = read_calibration_file(path, '/robot1/mag_calibrator')
    assert loaded.calibration.field_strength == 4.9e-5 and loaded.sections == (key,)
    applies = section_matches(key, '/robot1/mag_calibrator')
    assert bool(loaded.notes) is not applies  # a note exactly when --params-file would not
    if not applies:
        assert f'used section {key!r}, written for another node' in loaded.notes[0]


def fleet_file(path, *sections):
    path.write_text(''.join(
        calibration_yaml(fitted_calibration(robot=robot), node_name=key)
        for key, robot in sections))
    return path


def test_a_fleet_file_gives_each_robot_its_own_and_never_guesses(tmp_path):
    path = fleet_file(tmp_path / 'fleet.yaml', ('/robot1/mag_calibrator', 'one'),
                      ('/robot2/mag_calibrator', 'two'))
    assert load_calibration(path, '/robot1/mag_calibrator').metadata['robot'] == 'one'
    assert load_calibration(path, '/robot2/mag_calibrator').metadata['robot'] == 'two'
    with pytest.raises(CalibrationFileError, match='no calibration parameters for '
                       '/robot3/mag_calibrator .calibrations for '
                       "'/robot1/mag_calibrator', '/robot2/mag_calibrator'; keep the one to use"):
        load_calibration(path, '/robot3/mag_calibrator')


def test_sections_that_apply_are_merged_in_file_order_as_rcl_does(tmp_path):
    path = fleet_file(tmp_path / 'fleet.yaml', ('/**', 'any'), ('/robot1/mag_calibrator', 'one'))
    loaded = read_calibration_file(path, '/robot1/mag_calibrator')
    assert loaded.calibration.metadata['robot'] == 'one'  # the later section wins
    assert loaded.sections == ('/**', '/robot1/mag_calibrator')
    assert 'merged sections' in loaded.notes[0]
    assert load_calibration(path, '/robot2/mag_calibrator').metadata['robot'] == 'any'
    reversed_order = fleet_file(tmp_path / 'reversed.yaml', ('/robot1/mag_calibrator', 'one'),
                                ('/**', 'any'))
    assert load_calibration(reversed_order, '/robot1/mag_calibrator').metadata['robot'] == 'any'


def test_a_section_without_calibration_is_skipped(tmp_path):
    path = tmp_path / 'c.yaml'
    path.write_text('/robot1/mag_calibrator:\n  ros__parameters:\n    buffer_size: 150\n'
                    + calibration_yaml(fitted_calibration(), '/**'))
    loaded = read_calibration_file(path, '/robot1/mag_calibrator')
    assert loaded.sections == ('/**',) and loaded.notes == ()


@pytest.mark.parametrize('module', [calibration_file, params_yaml, safe_file])
def test_modules_never_import_rclpy(module):
    source = open(module.__file__, encoding='utf-8').read()
    assert not re.search(r'^\s*(import|from)\s+rclpy', source, flags=re.M)
