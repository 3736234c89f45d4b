# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""``InputSubscriptions``: the calibrator's subscriptions to the robot's own field's inputs.

``imu/temperature`` (sensor_msgs/Temperature, while ``use_temperature``) and each of
``interference_inputs`` (``topic:package/msg/Type:field``, ``calibration/live/inputs.py``), each
sample handed to the session's ``CompensationLearner`` in O(1). Follows the parameters: a
changed list subscribes anew. A type that cannot be imported is said once, in the user's terms,
and the other inputs still work.
"""

from __future__ import annotations

from collections.abc import Callable
import importlib
import importlib.util
from pathlib import Path

from rclpy.exceptions import InvalidTopicNameException
from rclpy.expand_topic_name import expand_topic_name
from rclpy.node import Node
from rclpy.validate_full_topic_name import validate_full_topic_name
from sensor_msgs.msg import Temperature

from mag_calibrator_ros.calibration.live.inputs import InputSpec, parse_input
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.nodes.runtime import guarded

TEMPERATURE_TOPIC = 'imu/temperature'
INPUT_EXAMPLES = {  # a published type: the interference_inputs entry that would learn from it
    'sensor_msgs/msg/BatteryState': 'current',
    'nav_msgs/msg/Odometry': 'abs(twist.twist.linear.x)',
}
"""config/mag_calibrator.yaml's examples, for the types a robot's graph most often has."""


def candidate_inputs(node: Node) -> list[str]:
    """interference_inputs entries for the topics of INPUT_EXAMPLES' types published now
    (``~/learn_compensation`` with none configured names them)."""
    return [f'{topic}:{kind}:{INPUT_EXAMPLES[kind]}'
            for topic, types in node.get_topic_names_and_types()
            for kind in types if kind in INPUT_EXAMPLES]


def magnetic_field_topics(node: Node, topic: str) -> list[str]:
    """While nothing publishes ``topic``, the sensor_msgs/MagneticField topics with a publisher
    now, calibrators' outputs (``.../mag_corrected``) aside: where a wrong remap or namespace
    should point instead. [] while ``topic`` has a publisher (the graph is not searched)."""
    if node.count_publishers(topic):
        return []
    return sorted(name for name, types in node.get_topic_names_and_types()
                  if 'sensor_msgs/msg/MagneticField' in types and name != topic
                  and not name.endswith('/mag_corrected') and node.count_publishers(name))


def learning_plan(node: Node, timeout_s: float) -> tuple[str, str]:
    """``~/learn_compensation``'s line as it starts (what it collects, for how long), and the
    note its answer ends with when no input is configured (the BatteryState and Odometry topics
    published now, as interference_inputs entries); '' with inputs."""
    inputs = list(node.get_parameter('interference_inputs').value)
    sources = [*inputs, *(['the die temperature']
                          if node.get_parameter('use_temperature').value else [])]
    note = ''
    if not inputs:
        candidates = ', '.join(f"'{entry}'" for entry in candidate_inputs(node))
        note = ('interference_inputs is empty; published now: '
                f'interference_inputs:=[{candidates}]' if candidates else
                'interference_inputs is empty, and no BatteryState or Odometry topic is '
                'published')
    return (f"learning the robot's own field for up to {timeout_s:g} s of readings, from "
            f"{', '.join(sources) or 'nothing'}" + (f' ({note})' if note else '')), note


def input_topic_problems(inputs: object, node_name: str = 'mag_calibrator',
                         namespace: str = '/') -> list[str]:
    """The ``interference_inputs`` whose topic rcl refuses (its own expansion and validation:
    the spec's pattern lets ``battery_c/`` through, and subscribing it raised in the executor
    at the next parameter change, issue #47)."""
    problems = []
    for text in inputs if isinstance(inputs, (list, tuple)) else ():
        spec = parse_input(text) if isinstance(text, str) else text
        if isinstance(spec, str):
            continue  # the settings' checks name the form
        try:
            validate_full_topic_name(expand_topic_name(spec.topic, node_name, namespace))
        except (InvalidTopicNameException, ValueError) as error:
            reason = str(error).split(', at /')[0].splitlines()[0]
            problems.append(f"interference input '{text}': {reason}")
    return problems


def _stamp_ns(message: object) -> int | None:
    """The message's header stamp in ns, None without a header (Twist) or with a zero stamp."""
    header = getattr(message, 'header', None)
    stamp = getattr(header, 'stamp', None)
    if stamp is None:
        return None
    value = stamp.sec * 1_000_000_000 + stamp.nanosec
    return value if value > 0 else None



def message_class(type_name: str) -> type:
    """The Python class of a ROS message type 'package/msg/Type' (or 'package/Type'), as
    rosidl_runtime_py's get_message finds it (that package has no PyPI wheel for the venv).
    A package without the ``msg`` subpackage rosidl generates is refused before anything of it
    runs: importing 'matplotlib/msg/X' stalled the executor for 386 ms (issue #47)."""
    package, _, name = type_name.replace('/msg/', '/').partition('/')
    found = importlib.util.find_spec(package) if package.isidentifier() else None
    if found is None or not any((Path(location) / 'msg' / '__init__.py').is_file()
                                for location in found.submodule_search_locations or ()):
        raise ImportError(f"no ROS interface package '{package}' (with a msg subpackage) is "
                          'installed')
    message = getattr(importlib.import_module(f'{package}.msg'), name)
    if not hasattr(message, 'get_fields_and_field_types'):
        raise ValueError(f'{type_name} is not a message type')
    return message

class InputSubscriptions:
    """Subscribes the temperature and the interference inputs the settings name."""

    def __init__(self, node: Node, session: CalibrationSession,
                 settings: Callable[[], SessionSettings], qos: object) -> None:
        self._node, self._session, self._qos = node, session, qos
        self._settings = settings  # the settings the session has now (the node keeps them)
        self._temperature = None
        self._inputs: list[object] = []
        self._wanted: tuple[tuple[str, ...], bool] | None = None
        self.problems: list[str] = []
        """Inputs that could not be subscribed (shown in the log)."""
        self.sync()  # and after each parameter change (the node calls it: rclpy runs
        # post-set callbacks newest first, and one of its own ran before the settings changed)

    def sync(self) -> None:
        """Subscribe what the session's settings name now (after a parameter change too)."""
        settings = self._settings()
        wanted = (tuple(settings.interference_inputs), settings.use_temperature)
        if wanted == self._wanted:
            return
        self._wanted = wanted
        node = self._node
        if settings.use_temperature and self._temperature is None:
            self._temperature = node.create_subscription(
                Temperature, TEMPERATURE_TOPIC,
                guarded(node, TEMPERATURE_TOPIC, self._on_temperature), self._qos)
        elif not settings.use_temperature and self._temperature is not None:
            node.destroy_subscription(self._temperature)
            self._temperature = None
        for subscription in self._inputs:
            node.destroy_subscription(subscription)
        self._inputs, self.problems = [], []
        for index, text in enumerate(settings.interference_inputs):
            spec = parse_input(text)
            if isinstance(spec, str):
                continue  # refused by the settings' checks already
            try:
                message_type = message_class(spec.type)
            except (AttributeError, ImportError, ValueError) as error:
                self.problems.append(
                    f"interference input '{text}': message type {spec.type} cannot be imported "
                    f'({error}); install its package or fix the name (package/msg/Type)')
                continue
            self._inputs.append(node.create_subscription(
                message_type, spec.topic,
                guarded(node, spec.topic, self._on_input(index, spec)), self._qos))
        for problem in self.problems:
            node.get_logger().error(problem)

    def _on_temperature(self, message: Temperature) -> None:
        self._session.process_temperature(_stamp_ns(message), message.temperature)

    def _on_input(self, index: int, spec: InputSpec) -> Callable[[object], None]:
        def on_message(message: object) -> None:
            self._session.process_input(index, _stamp_ns(message), spec.value(message))
        return on_message


__all__ = ['TEMPERATURE_TOPIC', 'InputSubscriptions', 'input_topic_problems']
