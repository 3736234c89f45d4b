# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Declaring parameters so that a bad value is a clear message, never a traceback; the
command line's ``--log-level <node name>:=...`` followed in a namespace too."""

from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy import logging
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter


class ConfigurationError(ValueError):
    """A node refuses to start: its parameters cannot work (already logged as FATAL)."""


def descriptor(
    description: str,
    *,
    read_only: bool = True,
    integer_range: tuple[int, int] | None = None,
    float_range: tuple[float, float] | None = None,
    constraints: str = '',
) -> ParameterDescriptor:
    """A parameter's descriptor in one call: read-only unless said, its range where it has one,
    so `ros2 param describe` tells users what rcl will refuse."""
    result = ParameterDescriptor(
        description=description, read_only=read_only, additional_constraints=constraints
    )
    if integer_range is not None:
        result.integer_range = [
            IntegerRange(from_value=integer_range[0], to_value=integer_range[1], step=0)
        ]
    if float_range is not None:
        result.floating_point_range = [
            FloatingPointRange(from_value=float_range[0], to_value=float_range[1], step=0.0)
        ]
    return result


def declare_checked(node: Node, name: str, default: object, descriptor: ParameterDescriptor,
                    problems: list[str]) -> object:
    """Declare ``name``; a value of the wrong type or outside the descriptor's range is noted in
    ``problems`` (and the default declared, so the node stays introspectable while it reports).
    """
    try:
        value = node.declare_parameter(name, default, descriptor).value
        if default == [] and not value:  # rcl gives an empty list no type (NOT_SET, or bytes)
            node.set_parameters([Parameter(name, Parameter.Type.STRING_ARRAY, [])])
            return []  # so `ros2 param get` says a list of strings, empty, as the YAML does
        return value
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


def follow_bare_log_level(node: Node) -> None:
    """``--log-level mag_calibrator:=debug`` reaches a node in a namespace too: its logger is
    ``<namespace>.<name>``, a child of the namespace's logger and not of the name users type,
    so a level set for the bare name alone is taken over (one set for the full name wins)."""
    logger, unset = node.get_logger(), logging.LoggingSeverity.UNSET
    bare = logging.get_logger_level(node.get_name())
    if logger.name != node.get_name() and bare != unset and (
            logging.get_logger_level(logger.name) == unset):
        logger.set_level(bare)
