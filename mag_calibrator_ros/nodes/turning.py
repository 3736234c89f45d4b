# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibrator turning the robot in place: ``~/rotate_and_calibrate``, ``~/stop_rotation``.

Every decision is the :class:`~mag_calibrator_ros.calibration.live.turning.TurnController`'s;
this wires it to a node: a timer every COMMAND_PERIOD_S publishes what it commands, every stop
path publishes zero at once (not at the next tick), and the publisher on ``cmd_vel`` exists only
while a turn runs (and for its zero hold), so the topic is left to teleop and navigation
otherwise. On shutdown the final zero waits, bounded, for the subscribers to acknowledge it.
The message type (``cmd_vel_stamped``) is chosen at each start: a stop's zeros go out in the
type the turn used, the type the base listens to.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
import time

from geometry_msgs.msg import Twist, TwistStamped
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.turning import (
    COMMAND_PERIOD_S,
    TurnController,
    TurnSettings,
)
from mag_calibrator_ros.nodes.runtime import guarded

COMMAND_TOPIC = 'cmd_vel'
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
"""Reliable: a stop must arrive (a best-effort subscriber still matches and gets the re-sends)."""
SHUTDOWN_ACK_S = 0.5
"""On shutdown, wait at most this long for subscribers to acknowledge the final zero."""
MAX_TICK_STEP_S = 2 * COMMAND_PERIOD_S
"""The most one look at the input adds to its age: a look later than that comes after a stall
of this node's executor, not of the magnetometer (see ``TurnInPlace._input_age``)."""
TURN_PARAMETERS = ('rotation_speed', 'rotation_acceleration', 'rotation_timeout')
"""The node's parameters that make the TurnSettings (their public names keep 'rotation')."""


def turn_settings_from(values: Mapping[str, object]) -> TurnSettings:
    """The TurnSettings of these parameter values (``rotation_speed`` ...)."""
    return TurnSettings(speed=float(values['rotation_speed']),
                        acceleration=float(values['rotation_acceleration']),
                        timeout_s=float(values['rotation_timeout']))


class TurnInPlace:
    """The ~/rotate_and_calibrate wiring of ``node``: services, timer, cmd_vel publisher.

    ``request_calibration(answered)`` asks ``session`` for a fit and calls ``answered`` with a
    Future of its attempt; ``answering(name, callback)`` makes a service callback that always
    answers. ``controller`` holds the state (diagnostics, tests).
    """

    def __init__(self, node: Node, session: CalibrationSession,
                 request_calibration: Callable[[Callable[[Future], None]], object],
                 answering: Callable[[str, Callable], Callable]) -> None:
        self._node = node
        self._session = session
        self._request_calibration = request_calibration
        self.controller = TurnController(
            turn_settings_from(self._parameter_values()),
            input_topic=node.resolve_topic_name('imu/mag'),
            command_topic=node.resolve_topic_name(COMMAND_TOPIC))
        self._publisher = None
        self._stamped = False
        self._accepted = 0  # readings accepted (``reading_accepted``) ...
        self._accepted_seen = 0  # ... and as the previous look saw them
        self._input_age_s: float | None = None  # executor time since the count last grew
        self._looked_at: float | None = None  # monotonic time of the previous look
        for name, callback in (('~/rotate_and_calibrate', self._on_rotate),
                               ('~/stop_rotation', self._on_stop_rotation)):
            node.create_service(Trigger, name, answering(name, callback))
        node.add_post_set_parameters_callback(self._parameters_changed)
        node.create_timer(COMMAND_PERIOD_S, guarded(node, 'rotation', self._on_timer))

    def reading_accepted(self) -> None:
        """The node's message callback: the session accepted a reading (O(1))."""
        self._accepted += 1

    def _parameter_values(self) -> dict[str, object]:
        return {name: self._node.get_parameter(name).value for name in TURN_PARAMETERS}

    # -- every COMMAND_PERIOD_S ------------------------------------------------------------------

    def _input_age(self, now: float) -> float | None:
        """Seconds since a reading was last accepted (looked at every COMMAND_PERIOD_S), each
        look adding at most MAX_TICK_STEP_S. A look that comes late comes after a stall of this
        executor (a loaded computer): the readings of that time wait in the subscription's
        queue, and rclpy runs a ready timer before them, so wall time would call a stall of the
        calibrator silence of the magnetometer and stop a turn for 'no input'. A magnetometer
        that stops is still seen within INPUT_HOLD_S of punctual looks."""
        step = 0.0 if self._looked_at is None else min(max(now - self._looked_at, 0.0),
                                                       MAX_TICK_STEP_S)
        self._looked_at = now
        if self._accepted != self._accepted_seen:
            self._accepted_seen = self._accepted
            self._input_age_s = 0.0
        elif self._input_age_s is not None:
            self._input_age_s += step
        return self._input_age_s

    def _other_commanders(self) -> int:
        publishers = self._node.count_publishers(self._node.resolve_topic_name(COMMAND_TOPIC))
        return publishers - (self._publisher is not None)

    def _on_timer(self) -> None:
        try:
            self._tick()
        except Exception:
            self.stop('error')  # never keep turning on an error; guarded logs it
            raise

    def _tick(self) -> None:
        now = time.monotonic()
        input_age = self._input_age(now)
        if self.controller.state == 'idle' and self._publisher is None:
            return
        step = self.controller.update(now, input_age, self._other_commanders(),
                                      self._session.heading_coverage)
        self._log(step.messages)
        if step.calibrate:
            self._request_calibration(self._fit_answered)  # may already have stopped the turn
        self._publish(self.controller.command(now))

    def _publish(self, yaw_rate: float | None) -> None:
        """Publish a turn command (None: nothing; the publisher goes once a stop's zeros are
        sent)."""
        node = self._node
        if yaw_rate is None:
            if self._publisher is not None:
                node.destroy_publisher(self._publisher)
                self._publisher = None
            return
        if self._publisher is None:
            self._publisher = node.create_publisher(
                TwistStamped if self._stamped else Twist, COMMAND_TOPIC, COMMAND_QOS)
        twist = Twist()
        twist.angular.z = float(yaw_rate)
        if self._stamped:
            message = TwistStamped(twist=twist)
            message.header.stamp = node.get_clock().now().to_msg()
            message.header.frame_id = str(node.get_parameter('cmd_vel_frame_id').value)
        else:
            message = twist
        self._publisher.publish(message)

    def _log(self, messages: Iterable[str | None]) -> None:
        for message in messages:
            if message:
                self._node.get_logger().info(message)

    # -- every way to stop -----------------------------------------------------------------------

    def stop(self, reason: str, detail: str = '') -> str | None:
        """Stop for ``reason`` and publish the zero at once (not at the next tick)."""
        now = time.monotonic()
        line = self.controller.stop(now, reason, detail)
        if line is not None:
            self._log([line])
            self._publish(self.controller.command(now))
        return line

    def _on_rotate(self, request: Trigger.Request, response: Trigger.Response):
        now = time.monotonic()
        started, message = self.controller.start(now, self._input_age(now),
                                                 self._other_commanders())
        if started:
            self._session.reset()  # a turn calibrates from what it sees, not older samples
            self._use_type(bool(self._node.get_parameter('cmd_vel_stamped').value))
            self._publish(self.controller.command(now))
            if self.controller.settings.caution():  # one call site per severity
                self._node.get_logger().warning(message)
            else:
                self._node.get_logger().info(message)
        else:
            self._node.get_logger().warning(f'~/rotate_and_calibrate refused: {message}')
        response.success, response.message = started, message
        return response

    def _use_type(self, stamped: bool) -> None:
        """Command in TwistStamped (or Twist) from now on. A publisher of the other type still
        holding a stop's zero goes: that zero was published when the turn stopped."""
        if stamped != self._stamped and self._publisher is not None:
            self._node.destroy_publisher(self._publisher)
            self._publisher = None
        self._stamped = stamped

    def _on_stop_rotation(self, request: Trigger.Request, response: Trigger.Response):
        line = self.stop('requested')
        response.success = True
        response.message = line or f'not rotating ({self.controller.progress_text(0.0)})'
        return response

    def _fit_answered(self, future: Future) -> None:
        attempt = future.result()
        error = attempt.outcome is not None and bool(attempt.outcome.error)
        now = time.monotonic()
        line = self.controller.calibration_answered(now, attempt.success, error, attempt.message)
        if line is not None:
            self._log([line])
            self._publish(self.controller.command(now))

    def _parameters_changed(self, parameters: list[Parameter]) -> None:
        self.controller.settings = turn_settings_from(self._parameter_values())
        changed = [p.name for p in parameters if not p.name.startswith('calibration.')]
        if changed:
            self.stop('parameters', ', '.join(changed))

    def stop_for_shutdown(self) -> None:
        """Zero on the way out, acknowledged by the subscribers if they can (bounded)."""
        try:
            self.stop('shutdown')
            publisher = self._publisher
            if publisher is not None:
                self._publish(0.0)
                publisher.wait_for_all_acked(Duration(nanoseconds=int(SHUTDOWN_ACK_S * 1e9)))
                self._node.destroy_publisher(publisher)
                self._publisher = None
        except Exception as error:  # noqa: BLE001 - shutting down: report, never raise
            self._node.get_logger().error(f'could not command zero on shutdown: {error!r}')
