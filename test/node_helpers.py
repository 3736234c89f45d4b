# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Shared helpers of the tests that run nodes over real rclpy/DDS: one context a module, every
node on its own thread, a probe user of the calibrator, bounded waits and service calls.

Imported by the test modules (``sys.path`` holds this folder); conftest's ``ros`` fixture builds
one ``Ros`` a module.
"""

from __future__ import annotations

from collections.abc import Callable
import math
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.live.worker import FitRunner
from mag_calibrator_ros.nodes.icm20948_driver import Icm20948DriverNode
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode
from mag_calibrator_ros.nodes.runtime import NodeThreads, wait_until

WAIT_S = 20.0


def wait_for(condition: Callable[[], bool], timeout_s: float = WAIT_S, step_s: float = 0.05
             ) -> bool:
    """Poll ``condition`` until true or ``timeout_s`` (a bound on waiting, not an assertion)."""
    return wait_until(condition, timeout_s, step_s)


class Ros:
    """One context for the module; every node spins on its own thread (see NodeThreads)."""

    def __init__(self) -> None:
        self.context = Context()
        rclpy.init(args=[], context=self.context)
        self.spinning = NodeThreads(self.context)

    def add(self, node: Node) -> Node:
        return self.spinning.add(node)

    def remove(self, node: Node) -> None:
        self.spinning.remove(node)

    def calibrator(self, namespace: str, runner: FitRunner | None = None, **parameters
                   ) -> MagCalibratorNode:
        """A calibrator node with these parameters; ``runner``: where its fits run (the node's
        own fit worker process by default)."""
        overrides = [Parameter(name, value=value) for name, value in parameters.items()]
        return self.add(MagCalibratorNode(
            namespace=namespace, context=self.context, parameter_overrides=overrides,
            runner=runner))

    def driver(self, namespace: str, **parameters) -> Icm20948DriverNode:
        values = {'backend': 'sim', 'rate_hz': 100, **parameters}
        overrides = [Parameter(name, value=value) for name, value in values.items()]
        return self.add(Icm20948DriverNode(
            namespace=namespace, context=self.context, parameter_overrides=overrides))

    def close(self) -> None:
        self.spinning.shutdown()
        rclpy.try_shutdown(context=self.context)


class Probe(Node):
    """A user of the calibrator: raw publisher, corrected subscriber, service clients."""

    def __init__(self, ros: Ros, namespace: str) -> None:
        super().__init__('probe', namespace=namespace, context=ros.context)
        self._lock = threading.Lock()
        self.raw: dict[tuple[int, int], np.ndarray] = {}
        self.corrected: list[MagneticField] = []
        self.diagnostics: list[DiagnosticStatus] = []
        self.publisher = self.create_publisher(MagneticField, 'imu/mag', 10)
        self.create_subscription(MagneticField, 'imu/mag', self._on_raw, 100)
        self.create_subscription(MagneticField, 'imu/mag_corrected', self._on_corrected, 100)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        ros.add(self)

    def _on_raw(self, msg: MagneticField) -> None:
        with self._lock:
            self.raw[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = vector(msg)

    def _on_corrected(self, msg: MagneticField) -> None:
        with self._lock:
            self.corrected.append(msg)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._lock:
            self.diagnostics.extend(msg.status)

    def take_corrected(self) -> list[MagneticField]:
        with self._lock:
            taken, self.corrected = self.corrected, []
        return taken

    def raw_for(self, msg: MagneticField) -> np.ndarray | None:
        with self._lock:
            return self.raw.get((msg.header.stamp.sec, msg.header.stamp.nanosec))

    def statuses(self, name_part: str) -> list[DiagnosticStatus]:
        with self._lock:
            return [s for s in self.diagnostics if name_part in s.name]

    def statuses_of(self, node: Node) -> list[DiagnosticStatus]:
        """The statuses ``node`` published: names carry its fully qualified name."""
        prefix = f'{node.get_fully_qualified_name()}: '
        with self._lock:
            return [s for s in self.diagnostics if s.name.startswith(prefix)]

    def call(self, service: str) -> Trigger.Response:
        return call_trigger(self, service)

    def send(self, field_t, sec: int, nanosec: int = 0, frame_id: str = 'imu_link',
             covariance=None) -> None:
        msg = MagneticField()
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.header.frame_id = frame_id
        msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = (
            float(v) for v in field_t)
        if covariance is not None:
            msg.magnetic_field_covariance = np.asarray(covariance, dtype=float).reshape(9)
        self.publisher.publish(msg)

    def connected_to(self, calibrator: Node) -> bool:
        return (self.publisher.get_subscription_count() >= 1
                and self.count_publishers(
                    calibrator.resolve_topic_name('imu/mag_corrected')) >= 1)


def accepted(calibrator: MagCalibratorNode) -> int:
    """Readings the calibrator's session accepted so far (its report, read from the test's
    thread: counts only, for waiting on)."""
    return calibrator.session.report().counts.accepted


def vector(msg: MagneticField) -> np.ndarray:
    return np.array([msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, cosine))))


def call_trigger(node: Node, service: str, timeout_s: float = WAIT_S) -> Trigger.Response:
    """Call a std_srvs/Trigger ``service`` from ``node`` (spinning elsewhere) and wait for the
    answer (at most ``timeout_s``); fails the test when the service never appears or never
    answers."""
    response = try_trigger(node, service, timeout_s)
    assert response is not None, f'{service} did not answer'
    return response


def try_trigger(node: Node, service: str, timeout_s: float = WAIT_S) -> Trigger.Response | None:
    """``call_trigger``, None when no answer came. A server that has just started may answer
    a brand-new client before it has discovered the client's response reader: Fast DDS waits
    for that match for the response writer's max_blocking_time (100 ms), then drops the
    response (rmw_fastrtps ``rmw_send_response``: 'client will not receive response'). On a
    busy machine a test of a freshly started process must judge such a call by its effect."""
    client = node.create_client(Trigger, service)
    assert client.wait_for_service(timeout_sec=WAIT_S), f'{service} not available'
    future = client.call_async(Trigger.Request())
    answered = wait_for(future.done, timeout_s)
    node.destroy_client(client)
    return future.result() if answered else None


def set_parameter_over_service(probe: Node, node: Node, name: str, value) -> tuple[bool, str]:
    service = f'{node.get_fully_qualified_name()}/set_parameters'
    client = probe.create_client(SetParameters, service)
    assert client.wait_for_service(timeout_sec=WAIT_S)
    parameter = Parameter(name, value=value).to_parameter_msg()
    future = client.call_async(SetParameters.Request(parameters=[parameter]))
    assert wait_for(future.done)
    probe.destroy_client(client)
    result = future.result().results[0]
    return result.successful, result.reason
