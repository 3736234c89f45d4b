# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ROS 2 parameters YAML text: strict typing on write, bounded parsing typed as rcl types it."""

import math
import re

from hypothesis import given
from hypothesis import strategies as st
import numpy as np
import pytest
import yaml

from mag_calibrator_ros.calibration.store import params_yaml
from mag_calibrator_ros.calibration.store.params_yaml import (
    MAX_DEPTH,
    MAX_FILE_BYTES,
    MAX_NODES,
    ParamsYamlError,
    double_text,
    parse_params_yaml,
    yaml_value,
)

LOADERS = [pytest.param(None, id='libyaml'),
           pytest.param(params_yaml._PythonLoader, id='python')]


def test_libyaml_is_used_when_present():
    assert yaml.__with_libyaml__, 'the pinned PyYAML wheel ships libyaml'
    assert params_yaml._Loader is params_yaml._LibyamlLoader


# -- hostile texts --------------------------------------------------------------------------------

BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + ''.join(
    f'{chr(98 + i)}: &{chr(98 + i)} [' + ','.join([f'*{chr(97 + i)}'] * 9) + ']\n'
    for i in range(8)
)


@pytest.mark.parametrize('loader', LOADERS)
@pytest.mark.parametrize(
    ('text', 'message'),
    [
        pytest.param('a: &x [*x]\n', 'anchors and aliases', id='self-referencing alias'),
        pytest.param(BILLION_LAUGHS, 'anchors and aliases', id='billion laughs'),
        pytest.param('a: &x 1\n', 'anchors and aliases', id='anchor'),
        pytest.param('a: *x\n', 'anchors and aliases', id='alias to nothing'),
        pytest.param('[' * 5000 + ']' * 5000, f'nested deeper than {MAX_DEPTH}', id='deep flow'),
        pytest.param(''.join(f'{" " * i}k:\n' for i in range(300)), 'nested deeper than',
                     id='deep block'),
        pytest.param('a: [' + ', '.join(['1.0'] * (MAX_NODES + 5)) + ']\n',
                     f'more than {MAX_NODES} values', id='too many values'),
        pytest.param('t: !!timestamp 2026-13-45\n', 'explicit YAML tags', id='timestamp tag'),
        pytest.param('x: !!python/object/apply:os.system ["true"]\n', 'explicit YAML tags',
                     id='python tag'),
        pytest.param('x: !!binary aGVsbG8=\n', 'explicit YAML tags', id='binary tag'),
        pytest.param('a: [\n', r'not valid YAML at line \d+, column \d+', id='unclosed'),
        pytest.param('a:\n\tb: 1\n', 'not valid YAML', id='tab'),
        pytest.param('a: 1\n---\nb: 2\n', 'not valid YAML', id='two documents'),
        pytest.param('? [a, b]\n: 1\n', 'not valid YAML', id='unhashable key'),
        pytest.param('a: "\x01"\n', 'not valid YAML', id='control character'),
        pytest.param('x' * (MAX_FILE_BYTES + 1), f'longer than {MAX_FILE_BYTES}', id='too long'),
    ],
)
def test_hostile_texts_are_refused_with_a_reason(text, message, loader):
    with pytest.raises(ParamsYamlError, match=message):
        parse_params_yaml(text, loader)


@pytest.mark.parametrize('loader', LOADERS)
def test_the_limits_are_exact_and_leave_room_for_real_files(loader):
    def nested(levels):  # levels - 1 mappings around one scalar
        return '{a: ' * (levels - 1) + '1' + '}' * (levels - 1)

    assert parse_params_yaml(nested(MAX_DEPTH), loader)['a']['a']
    with pytest.raises(ParamsYamlError, match='nested deeper'):
        parse_params_yaml(nested(MAX_DEPTH + 1), loader)
    many = 'a: [' + ', '.join(['1.0'] * (MAX_NODES - 10)) + ']\n'
    assert len(parse_params_yaml(many, loader)['a']) == MAX_NODES - 10


# -- typing as rcl types it -----------------------------------------------------------------------


@pytest.mark.parametrize('loader', LOADERS)
@pytest.mark.parametrize(
    ('scalar', 'expected'),
    [
        # what rcl (Jazzy, --params-file) made of each, checked with rclpy
        ('2026-13-45', '2026-13-45'),            # not a date: PyYAML alone raises ValueError
        ('2026-01-01', '2026-01-01'),            # rcl: STRING
        ('2026-01-01T00:00:00Z', '2026-01-01T00:00:00Z'),
        ('9223372036854775807', 9223372036854775807),  # int64 max: INTEGER
        ('12345678901234567890123', 1.2345678901234568e22),  # beyond int64: DOUBLE
        ('-' + '9' * 30, -1e30),
        ('1' * 5000, '1' * 5000),                # beyond a double: STRING (PyYAML: ValueError)
        ('1' * 400 + '.0', '1' * 400 + '.0'),    # beyond a double: STRING
        ('.inf', math.inf),
        ('-.inf', -math.inf),
        ('1e-06', 1e-06),                        # YAML 1.1 alone: a string
        ('-2E+5', -2e5),
        ('0x10', 16),
        ('on', True),
        ('"on"', 'on'),
    ],
)
def test_scalars_are_typed_as_rcl_types_them(scalar, expected, loader):
    value = parse_params_yaml(f'v: {scalar}\n', loader)['v']
    assert type(value) is type(expected) and value == expected


@pytest.mark.parametrize('loader', LOADERS)
@given(text=st.text(alphabet='ab:-[]{}&*!|>"\'#,.\n 0123456789\t?%@`~', max_size=300))
def test_any_text_parses_or_raises_params_yaml_error(loader, text):
    try:
        parse_params_yaml(text, loader)
    except ParamsYamlError:
        pass


# -- writing --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    'value', [1.0, 0.0, -3.0, 50.0, 1e17, 1e-7, 5e-05, 123456789.0, 1e300, -2.5e-310]
)
def test_doubles_always_carry_a_decimal_point_or_exponent(value):
    text = double_text(value)
    assert re.fullmatch(r'-?\d+\.\d*(e[-+]\d+)?', text), text
    assert yaml.safe_load(text) == value and type(yaml.safe_load(text)) is float


def test_array_types_are_never_mixed():
    assert yaml_value([1, 2.5]) == '[1.0, 2.5]'  # rcl refuses [1, 2.5]
    assert yaml_value([True, 1]) == '["True", "1"]'
    assert yaml_value([[1, 2], [3]]) == '["[1, 2]", "[3]"]'  # rcl refuses nested sequences
    assert yaml_value(np.array([1, 2])) == '[1, 2]'
    assert yaml_value([]) is None and yaml_value(None) is None
    assert yaml_value(2**70) == double_text(float(2**70))  # rcl reads it as a double anyway


@pytest.mark.parametrize(
    'value', [[0.0] * 10**7, np.zeros(10**7), 'x' * (MAX_FILE_BYTES + 1), 10**400],
    ids=['long list', 'long array', 'long text', 'huge integer'],
)
def test_the_writer_refuses_runaway_values_at_once(value):
    with pytest.raises(ParamsYamlError, match='too many|too long|out of range'):
        params_yaml.params_yaml('/**', {'calibration': {'v': value}})


def test_the_writer_refuses_self_reference():
    looped: dict = {}
    looped['again'] = looped
    with pytest.raises(ParamsYamlError, match='nested too deeply'):
        params_yaml.params_yaml('/**', {'calibration': looped})
