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
from functools import cached_property
import math
import re

SPEC = re.compile(r'^(?P<topic>~?/?[A-Za-z_][\w/]*):(?P<type>[A-Za-z_]\w*/(?:msg/)?[A-Za-z_]\w*)'
                  r':(?P<abs>abs\()?(?P<path>[A-Za-z_]\w*(?:\[\d+\])?(?:\.[A-Za-z_]\w*'
                  r'(?:\[\d+\])?)*)(?(abs)\))$')
"""``topic:package/msg/Type:field`` (see the module docstring)."""
MAX_INPUTS = 8

KIND_LIMITS = (('current', 1000.0, 'A'), ('voltage', 1000.0, 'V'), ('linear', 100.0, 'm/s'),
               ('angular', 100.0, 'rad/s'), ('velocity', 1000.0, 'per s'),
               ('effort', 1e4, 'N or N m'))
"""The largest size each kind of input takes on any robot (the first kind a field's path or
name contains): a 1000 A pack current or a 100 m/s speed is none; other fields up to
ANY_LIMIT. A battery driver's "unknown" (65535) lies beyond them (issue #47)."""
ANY_LIMIT = 1e6
SENTINELS = frozenset({65535.0, 32767.0, -32767.0, -32768.0})
"""Integer "unknown" values drivers put in float fields (UINT16_MAX, INT16_MAX/MIN), refused
in every kind (sensor_msgs/BatteryState's own "unmeasured" is NaN)."""


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

    @cached_property
    def kind(self) -> tuple[str, float, str]:
        """(kind, largest size, unit) of KIND_LIMITS this input's field is, found once."""
        words = re.findall(r'[a-z]+', ' '.join(self.path or (self.text,)).lower())
        return next((kind for kind in KIND_LIMITS if any(kind[0] in word for word in words)),
                    ('value', ANY_LIMIT, ''))

    def sample_problem(self, value: float) -> str | None:
        """Why ``value`` is no sample of this input (non-finite, a sentinel, beyond its kind's
        size), or None."""
        if not math.isfinite(value):
            return None if math.isnan(value) else f'{value} is not a number it can take'
        kind, limit, unit = self.kind
        if value in SENTINELS:
            return f'{value:g} is a driver\'s "unknown" value, not a measurement'
        if abs(value) > limit:
            return f"{value:g} is beyond any robot's {kind} ({limit:g} {unit})".replace(' )', ')')
        return None


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


__all__ = ['ANY_LIMIT', 'KIND_LIMITS', 'MAX_INPUTS', 'SENTINELS', 'InputSpec', 'input_problems',
           'parse_input']
