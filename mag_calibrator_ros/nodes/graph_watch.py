# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Other nodes that would double the corrected field (issue #46): a second publisher on
``imu/mag_corrected`` (two calibrators in one namespace: fusion gets every reading twice, stamps
going backwards), or another calibrator correcting the same raw input. Read from the ROS graph
once a diagnostics period; the text goes to /diagnostics as a WARN and to the log when it
changes."""

from __future__ import annotations

from collections.abc import Sequence

from rclpy._rclpy_pybind11 import NodeNameNonExistentError, RCLError
from rclpy.node import Node

MAGNETIC_FIELD = 'sensor_msgs/msg/MagneticField'
CORRECTED_NAME = 'mag_corrected'


def qualified(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


def doubled_text(output_topic: str, own: str, publishers: Sequence[str], input_topic: str,
                 calibrators: Sequence[tuple[str, str]]) -> str:
    """The warning for the other publishers on ``output_topic`` (fully qualified node names,
    this node ``own`` once for itself) and the other ``calibrators`` (name, the corrected topic
    it publishes) on ``input_topic``; '' when there are none."""
    others = list(publishers)
    if own in others:
        others.remove(own)
    if others:
        names = ', '.join(sorted(others))
        same = ' (the same name: started twice?)' if own in others else ''
        return (f'{output_topic} has another publisher: {names}{same}; subscribers get every '
                'reading twice: stop one, or give each its own namespace')
    if calibrators:
        names = ', '.join(f'{name} (publishes {topic})'
                          for name, topic in sorted(set(calibrators)))
        return (f'another calibrator corrects {input_topic} too: {names}; if that is not '
                'meant, stop one')
    return ''


class GraphWatch:
    """Asks the graph who else publishes this node's output or corrects its input."""

    def __init__(self) -> None:
        self.text = ''

    def check(self, node: Node, input_topic: str, output_topic: str) -> str:
        """The warning now ('' alone), logged when it changes (once as it starts, once as it
        ends)."""
        own = node.get_fully_qualified_name()
        publishers = [qualified(info.node_namespace, info.node_name)
                      for info in node.get_publishers_info_by_topic(output_topic)
                      if info.node_namespace.startswith('/')]
        calibrators = []
        for info in node.get_subscriptions_info_by_topic(input_topic):
            name = qualified(info.node_namespace, info.node_name)
            if name == own or not info.node_namespace.startswith('/'):
                continue  # (DDS names an endpoint's node '_NODE_NAMESPACE_UNKNOWN_' at first)
            try:
                published = node.get_publisher_names_and_types_by_node(info.node_name,
                                                                       info.node_namespace)
            except (NodeNameNonExistentError, RCLError):  # it left between the two questions
                continue
            calibrators.extend(
                (name, topic) for topic, types in published
                if topic.rsplit('/', 1)[-1] == CORRECTED_NAME and MAGNETIC_FIELD in types)
        text = doubled_text(output_topic, own, publishers, input_topic, calibrators)
        if text and text != self.text:  # one call site per severity
            node.get_logger().warning(text)
        elif self.text and not text:
            node.get_logger().info(f'{output_topic}: no other node doubles it now')
        self.text = text
        return text
