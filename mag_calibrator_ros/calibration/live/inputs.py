# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Interference inputs named by parameter: ``topic:package/msg/Type:field``.

``battery_state:sensor_msgs/msg/BatteryState:current`` (a battery current),
``cmd_vel:geometry_msgs/msg/Twist:abs(linear.x)`` (a commanded speed as a proxy when no current
is measured), ``odom:nav_msgs/msg/Odometry:abs(twist.twist.angular.z)``,
``joint_states:sensor_msgs/msg/JointState:effort[0]``: the field is a dotted path with optional
indices, ``abs(...)`` when only the size matters (a motor draws current either way). The node
subscribes them (``nodes/inputs.py``); ``live/compensation.py`` pairs their values with readings.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import re

SPEC = re.compile(r'^(?P<topic>~?/?[A-Za-z_][\w/]*):(?P<type>[A-Za-z_]\w*/(?:msg/)?[A-Za-z_]\w*)'
                  r':(?P<abs>abs\()?(?P<path>[A-Za-z_]\w*(?:\[\d+\])?(?:\.[A-Za-z_]\w*'
                  r'(?:\[\d+\])?)*)(?(abs)\))$')
"""``topic:package/msg/Type:field`` (see the module docstring)."""
MAX_INPUTS = 8


@dataclass(frozen=True)
class InputSpec:
    """One interference input: the topic, its message type and the field read from it."""

    topic: str
    type: str
    path: tuple[str, ...]
    absolute: bool
    text: str

    def value(self, message: object) -> float:
        """The field's value in ``message`` (NaN when absent or not a number)."""
        value = message
        try:
            for part in self.path:
                name, _, index = part.partition('[')
                value = getattr(value, name)
                if index:
                    value = value[int(index[:-1])]
            number = float(value)
        except (AttributeError, IndexError, TypeError, ValueError):
            return math.nan
        return abs(number) if self.absolute else number


def parse_input(text: str) -> InputSpec | str:
    """An input spec, or why ``text`` is none (a message naming the form)."""
    match = SPEC.match(text.strip()) if isinstance(text, str) else None
    if match is None:
        return (f'interference input {text!r} is not topic:package/msg/Type:field (e.g. '
                "'battery_state:sensor_msgs/msg/BatteryState:current' or "
                "'cmd_vel:geometry_msgs/msg/Twist:abs(linear.x)')")
    package, _, name = match['type'].replace('/msg/', '/').partition('/')
    return InputSpec(match['topic'], f'{package}/msg/{name}', tuple(match['path'].split('.')),
                     bool(match['abs']), text.strip())


def input_problems(inputs: tuple[str, ...]) -> list[str]:
    """Everything wrong with ``interference_inputs`` (SessionSettings.problems)."""
    if isinstance(inputs, str) or not all(isinstance(text, str) for text in inputs):
        return [f'interference_inputs must be a list of strings, got {inputs!r}']
    problems = [spec for spec in map(parse_input, inputs) if isinstance(spec, str)]
    if len(inputs) > MAX_INPUTS:
        problems.append(f'interference_inputs: at most {MAX_INPUTS}, got {len(inputs)}')
    if len(set(inputs)) != len(inputs):
        problems.append('interference_inputs names an input twice')
    return problems


__all__ = ['MAX_INPUTS', 'InputSpec', 'input_problems', 'parse_input']
