"""Declaring parameters so that a bad value is a clear message, never a traceback."""

from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node


class ConfigurationError(ValueError):
    """A node refuses to start: its parameters cannot work (already logged as FATAL)."""


def declare_checked(node: Node, name: str, default: object, descriptor: ParameterDescriptor,
                    problems: list[str]) -> object:
    """Declare ``name``; a value of the wrong type or outside the descriptor's range is noted in
    ``problems`` (and the default declared, so the node stays introspectable while it reports).
    """
    try:
        return node.declare_parameter(name, default, descriptor).value
    except (InvalidParameterValueException, InvalidParameterTypeException) as error:
        expected = type(default).__name__
        if isinstance(default, list):
            expected = f'list of {len(default)} {type(default[0]).__name__}s'
        problems.append(f'{name}: {error} (expected {expected}: {descriptor.description})')
        return node.declare_parameter(name, default, descriptor, ignore_override=True).value


def refuse_to_start(node: Node, problems: list[str]) -> None:
    """Log every problem as one FATAL message and raise ConfigurationError."""
    message = 'refusing to start, invalid parameters:\n  ' + '\n  '.join(problems)
    node.get_logger().fatal(message)
    raise ConfigurationError(message)
