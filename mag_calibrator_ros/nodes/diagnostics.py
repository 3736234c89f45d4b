# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""diagnostic_msgs helpers (diagnostic_updater has no PyPI wheel for Jazzy)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

DIAGNOSTICS_TOPIC = '/diagnostics'
# DiagnosticStatus levels are single bytes in rclpy messages (b'\x00' ...).
OK: bytes = DiagnosticStatus.OK
WARN: bytes = DiagnosticStatus.WARN
ERROR: bytes = DiagnosticStatus.ERROR
STALE: bytes = DiagnosticStatus.STALE


def format_value(value: object) -> str:
    """Diagnostics values are strings: floats get 4 significant digits, the rest ``str()``."""
    if isinstance(value, float):
        return f'{value:.4g}'
    return str(value)


def diagnostic_status(
    name: str,
    hardware_id: str,
    level: bytes,
    message: str,
    values: Mapping[str, object],
) -> DiagnosticStatus:
    """One status entry; ``level`` is OK, WARN, ERROR or STALE from this module."""
    return DiagnosticStatus(
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=str(k), value=format_value(v)) for k, v in values.items()],
    )


class DiagnosticsPublisher:
    """Publishes DiagnosticArray on ``/diagnostics`` as diagnostic_updater would."""

    def __init__(self, node: Node) -> None:
        self._node = node
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self._publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, qos)

    def publish(self, statuses: Iterable[DiagnosticStatus]) -> None:
        array = DiagnosticArray()
        array.header.stamp = self._node.get_clock().now().to_msg()
        array.status = list(statuses)
        self._publisher.publish(array)
