# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Ground robots over real rclpy/DDS: the simulated robot follows cmd_vel (sim.motion cmd_vel),
the calibrator turns it with ~/rotate_and_calibrate, and every way a rotation ends commands zero
-- seen by a subscriber and by the simulated robot coming to rest (the loop closed). A robot
turned by other means calibrating by itself is replayed without a graph in
test_ground_replays.py."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist, TwistStamped
import pytest
from rclpy.node import Node
from std_srvs.srv import Trigger

from mag_calibrator_ros.calibration.live.jobs import JobOutcome
from mag_calibrator_ros.calibration.live.session import SessionEvent
from mag_calibrator_ros.calibration.live.worker import InlineRunner
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode

sys.path.insert(0, str(Path(__file__).parent))
from node_helpers import (  # noqa: E402  (the DDS helpers, one place)
    Ros,
    accepted,
    call_trigger,
    set_parameter_over_service,
    try_trigger,
    wait_for,
)
from test_ground_session import heading_error_deg  # noqa: E402
from test_heading import HARD_IRON_UT, SOFT_IRON  # noqa: E402

SIM_SEED = 9  # heading_error_deg evaluates the same floor on another turn
CALIBRATION_S = 120.0  # bound on waiting for a whole turn under load (not a timing assertion)


class Commander(Node):
    """Listens on cmd_vel (Twist or TwistStamped), calls services, reads diagnostics; given the
    calibrator (in this process), also keeps what its turn decided to publish."""

    def __init__(self, ros: Ros, namespace: str, stamped: bool = False,
                 calibrator: MagCalibratorNode | None = None) -> None:
        super().__init__('commander', namespace=namespace, context=ros.context)
        self._lock = threading.Lock()
        self.twists: list[tuple[float, float]] = []  # (monotonic receipt, angular z)
        self.decided = None if calibrator is None else watch_commands(calibrator)
        self.diagnostics: list[str] = []
        kind = TwistStamped if stamped else Twist
        self.create_subscription(kind, 'cmd_vel', self._on_twist, 50)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        ros.add(self)

    def _on_twist(self, message) -> None:
        twist = message.twist if isinstance(message, TwistStamped) else message
        with self._lock:
            self.twists.append((time.monotonic(), twist.angular.z))

    def _on_diagnostics(self, message: DiagnosticArray) -> None:
        with self._lock:
            for status in message.status:
                # This robot's calibrator only: /diagnostics carries every node's status.
                if self.get_namespace() in status.hardware_id and 'calibration' in status.name:
                    values = ' '.join(f'{kv.key}={kv.value}' for kv in status.values
                                      if kv.key == 'coverage_hint')
                    self.diagnostics.append(f'{status.message} {values}')

    def last_twist(self) -> float | None:
        with self._lock:
            return self.twists[-1][1] if self.twists else None

    def twists_since(self, moment: float) -> list[float]:
        with self._lock:
            return [z for t, z in self.twists if t >= moment]

    def call(self, service: str) -> Trigger.Response:
        return call_trigger(self, service)


def watch_commands(calibrator: MagCalibratorNode) -> list[tuple[str, float | None]]:
    """(the turn's state, the yaw rate) of every command the calibrator publishes, recorded on
    its own thread as it publishes: which zeros are the stop's is then known, not guessed from
    arrival times (a hold's zeros come before it, and arrivals lag on a loaded computer)."""
    turning = calibrator._turning
    publish, controller = turning._publish, turning.controller
    decided: list[tuple[str, float | None]] = []

    def recorded(yaw_rate: float | None) -> None:
        decided.append((controller.state, yaw_rate))
        publish(yaw_rate)

    turning._publish = recorded
    return decided


def after_the_stop(decided: list[tuple[str, float | None]]) -> list[float | None] | None:
    """The commands published from the latest stop on (None: no stop published yet)."""
    stops = [i for i, (state, _) in enumerate(decided)
             if state == 'stopping' and (i == 0 or decided[i - 1][0] == 'turning')]
    return [rate for _, rate in decided[stops[-1]:]] if stops else None


def sim_robot(ros: Ros, namespace: str, **parameters):
    return ros.driver(namespace, **{
        'sim.motion': 'cmd_vel', 'sim.seed': SIM_SEED, 'sim.hard_iron_ut': list(HARD_IRON_UT),
        'sim.soft_iron': SOFT_IRON.reshape(-1).tolist(), **parameters})


def yaw_rate(driver) -> float:
    return driver.settings.cmd_vel.yaw_and_rate(driver.simulator.sim_time_s)[1]


def turning_robot(ros: Ros, tmp_path: Path, namespace: str, **calibrator_parameters):
    """A sim robot, a calibrator and a commander, the rotation started and the robot turning."""
    driver = sim_robot(ros, namespace)
    calibrator = ros.calibrator(namespace, calibration_file=str(tmp_path / 'c.yaml'),
                                progress_log_period=0.0, **calibrator_parameters)
    commander = Commander(ros, namespace, calibrator=calibrator)
    assert wait_for(lambda: accepted(calibrator) > 20)
    response = commander.call('mag_calibrator/rotate_and_calibrate')
    assert response.success, response.message
    assert wait_for(lambda: yaw_rate(driver) > 0.05), 'the simulated robot never turned'
    return driver, calibrator, commander


def brought_to_rest(commander: Commander, driver, moment: float) -> None:
    """A zero arrived after ``moment``, the calibrator published nothing but zeros from its stop
    on (when the commander watches it), the last command is zero, and the robot stopped."""
    assert wait_for(lambda: 0.0 in commander.twists_since(moment)), 'no zero twist'
    if commander.decided is not None:
        assert wait_for(lambda: after_the_stop(commander.decided) is not None), 'no stop'
        after = after_the_stop(commander.decided)
        assert after[0] == 0.0 and set(after) <= {0.0, None}, after
    assert wait_for(lambda: commander.last_twist() == 0.0), commander.twists_since(moment)[-5:]
    if driver is not None:
        assert wait_for(lambda: yaw_rate(driver) == 0.0), 'the simulated robot kept turning'


def remove_all(ros: Ros, *nodes) -> None:
    for node in nodes:
        if node is not None:
            ros.remove(node)


def test_rotate_and_calibrate_turns_the_robot_until_calibrated_and_stops(ros, tmp_path):
    # Twice the default speed (the sim robot's limit is 1 rad/s): the same circle in half the
    # time; the default speed and its ramp are test_turning.py's
    namespace = 'ground_done'
    driver, calibrator, commander = turning_robot(ros, tmp_path, namespace, rotation_speed=0.6)
    start_yaw = driver.settings.cmd_vel.yaw_and_rate(driver.simulator.sim_time_s)[0]
    assert wait_for(lambda: calibrator._rotation.state == 'idle', timeout_s=CALIBRATION_S), (
        calibrator._rotation.progress_text(time.monotonic()))
    reason, message = calibrator._rotation.last_stop
    assert reason == 'done', message
    assert calibrator.session.calibration.model == 'planar'
    assert commander.last_twist() == 0.0
    assert wait_for(lambda: yaw_rate(driver) == 0.0)
    turned = math.degrees(abs(
        driver.settings.cmd_vel.yaw_and_rate(driver.simulator.sim_time_s)[0] - start_yaw))
    # The circle, then a stop. How far past the circle it turns while the fit runs depends on the
    # machine's load (a timing, measured by bench_ground), so only the circle is asserted here.
    assert turned >= 300.0
    speeds = [abs(z) for _, z in commander.twists]
    assert max(speeds) == pytest.approx(0.6) and min(speeds) < 0.1  # a ramp from standstill
    error = heading_error_deg(calibrator.session.calibration, seed=SIM_SEED)
    print(f'rotate_and_calibrate: {message}; turned {turned:.0f} deg; heading error '
          f'{error:.2f} deg RMS (noise-free, over a turn)')
    assert error < 3.0  # 2 deg of heading-locked wobble at 60 deg: fit/levelled.py
    remove_all(ros, commander, calibrator, driver)


def test_stop_rotation_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_stop')
    moment = time.monotonic()
    response = commander.call('mag_calibrator/stop_rotation')
    assert response.success and 'stopped on request' in response.message
    brought_to_rest(commander, driver, moment)
    again = commander.call('mag_calibrator/stop_rotation')
    assert again.success and again.message.startswith('not rotating')
    remove_all(ros, commander, calibrator, driver)


def test_the_timeout_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_timeout',
                                                  rotation_timeout=5.0, rotation_speed=0.1)
    moment = time.monotonic()
    assert wait_for(lambda: calibrator._rotation.state != 'turning', timeout_s=60.0)
    assert calibrator._rotation.last_stop[0] == 'timeout'
    brought_to_rest(commander, driver, moment)
    remove_all(ros, commander, calibrator, driver)


def test_losing_the_magnetometer_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_input')
    moment = time.monotonic()
    ros.remove(driver)  # the sensor is gone: the robot must not turn blind
    assert wait_for(lambda: calibrator._rotation.state != 'turning')
    assert calibrator._rotation.last_stop[0] == 'no_input'
    brought_to_rest(commander, None, moment)
    remove_all(ros, commander, calibrator)


def test_a_stall_of_the_calibrator_is_no_loss_of_input(ros, tmp_path):
    """On a loaded machine the calibrator's executor stalled for 0.5-1.1 s while the driver kept
    publishing, right after a look at the input: its readings waited in the subscription's queue
    behind the turn's timer, which rclpy runs first, saw 0.5 s without input and stopped the
    turn for 'no_input' (the rotate_and_calibrate test failed so). A stall now counts as one
    late look at the input."""
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_stall')
    turning, stalled = calibrator._turning, threading.Event()
    tick = turning._tick

    def stalled_once() -> None:
        if not stalled.is_set():
            # As seen under load: the look before the stall had taken in every reading
            # processed so far (rclpy then ran no subscription before stalling), ...
            turning._accepted_seen = turning._accepted
            time.sleep(0.8)  # ... and the executor ran nothing for 0.8 s: readings queue up
            stalled.set()
        tick()  # the timer runs before the queued readings

    turning._tick = stalled_once
    assert stalled.wait(timeout=30.0)
    seen = accepted(calibrator)
    assert wait_for(lambda: accepted(calibrator) > seen + 50)
    assert calibrator._rotation.last_stop is None, calibrator._rotation.last_stop
    assert calibrator._rotation.state == 'turning'
    moment = time.monotonic()
    assert commander.call('mag_calibrator/stop_rotation').success
    brought_to_rest(commander, driver, moment)
    remove_all(ros, commander, calibrator, driver)


def test_a_pause_of_the_driver_holds_the_turn_until_readings_come_back(ros, tmp_path):
    """On a loaded computer the driver's thread waited 0.3-0.8 s for a core while the
    calibrator's ran on (docs/BENCHMARKS.md, "A pause of the driver holds a turn"): 0.5 s of
    punctual looks without a reading stopped the turn for 'no_input'. A pause now holds the
    robot still (zero) until readings come back, then the turn ramps up again."""
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_pause')
    supervisor, rotation = driver.supervisor, calibrator._rotation
    step, paused = supervisor.step, threading.Event()

    def paused_once():
        if not paused.is_set():
            paused.set()  # this thread gets no core: nothing is read until the turn holds
            wait_for(lambda: rotation.holding, timeout_s=60.0)
        return step()

    supervisor.step = paused_once
    assert paused.wait(timeout=30.0)
    moment = time.monotonic()

    def zero_then_turning() -> bool:
        after = commander.twists_since(moment)
        return 0.0 in after and any(z > 0.0 for z in after[after.index(0.0):])

    assert wait_for(zero_then_turning, timeout_s=60.0), commander.twists_since(moment)[-5:]
    assert rotation.last_stop is None, rotation.last_stop
    assert rotation.state == 'turning' and not rotation.holding
    moment = time.monotonic()
    assert commander.call('mag_calibrator/stop_rotation').success
    brought_to_rest(commander, driver, moment)
    remove_all(ros, commander, calibrator, driver)


class FailingRequests(InlineRunner):
    """Fits inline, but every requested fit fails with an error (as if the worker died)."""

    def submit(self, job) -> None:
        if job.ticket is None:
            super().submit(job)
        else:
            self._outcome = JobOutcome(job, error='injected: fit worker process ended')


def test_a_fit_error_commands_zero(ros, tmp_path):
    driver = sim_robot(ros, 'ground_error')
    # A quicker turn than the default, the sim robot's limit of 1 rad/s and its ramp (the
    # circle is what the fit waits for): the stop is the same at any speed.
    calibrator = ros.calibrator('ground_error', runner=FailingRequests(),
                                calibration_file=str(tmp_path / 'c.yaml'),
                                auto_calibrate=False, rotation_speed=1.0,
                                rotation_acceleration=1.0)
    commander = Commander(ros, 'ground_error', calibrator=calibrator)
    assert wait_for(lambda: accepted(calibrator) > 20)
    assert commander.call('mag_calibrator/rotate_and_calibrate').success
    assert wait_for(lambda: yaw_rate(driver) > 0.05)
    moment = time.monotonic()
    assert wait_for(lambda: calibrator._rotation.state != 'turning', timeout_s=CALIBRATION_S)
    reason, message = calibrator._rotation.last_stop
    assert reason == 'fit_error' and 'injected' in message
    brought_to_rest(commander, driver, moment)
    assert commander.call('mag_calibrator/stop_rotation').success  # the node still answers
    remove_all(ros, commander, calibrator, driver)


def test_an_unexpected_error_in_the_rotation_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_bug')

    def broken():
        raise RuntimeError('injected bug')

    calibrator.session.heading_coverage = broken  # the rotation looks at it every 0.5 s
    moment = time.monotonic()
    assert wait_for(lambda: calibrator._rotation.state != 'turning', timeout_s=CALIBRATION_S)
    assert calibrator._rotation.last_stop[0] == 'error'
    brought_to_rest(commander, driver, moment)
    assert commander.call('mag_calibrator/stop_rotation').success  # the node still answers
    remove_all(ros, commander, calibrator, driver)


def test_session_events_of_every_level_are_logged_from_one_node(ros, tmp_path):
    """rclpy refuses a severity change at one logging call site: an info event, then a warning
    (a calibration, then a failed rotation fit) once crashed the node's event handling."""
    calibrator = ros.calibrator('ground_events', runner=InlineRunner(),  # no fit here
                                calibration_file=str(tmp_path / 'c.yaml'))
    session, handed = calibrator.session, []

    def events_of(level: str):
        def take() -> list[SessionEvent]:
            handed.append(level)
            return [SessionEvent(level, f'a {level} event')]
        return take

    levels = ('info', 'warning', 'debug', 'info', 'warning')
    for level in levels:
        session.take_events = events_of(level)  # what the session decided, one level a time
        calibrator._handle_events()  # raised ValueError on the second level before the fix
    del session.take_events  # the session's own again
    assert set(handed) == set(levels) and handed[-1] == 'warning'
    ros.remove(calibrator)


def test_a_parameter_change_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_params')
    moment = time.monotonic()
    ok, reason = set_parameter_over_service(commander, calibrator, 'rotation_speed', 0.5)
    assert ok, reason
    assert calibrator._rotation.last_stop[0] == 'parameters'
    brought_to_rest(commander, driver, moment)
    remove_all(ros, commander, calibrator, driver)


def test_another_commander_appearing_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_conflict')
    teleop = commander.create_publisher(Twist, 'cmd_vel', 10)  # silent, but there
    moment = time.monotonic()
    assert wait_for(lambda: calibrator._rotation.state != 'turning')
    assert calibrator._rotation.last_stop[0] == 'conflict'
    brought_to_rest(commander, driver, moment)
    commander.destroy_publisher(teleop)
    remove_all(ros, commander, calibrator, driver)


def test_destroying_the_node_commands_zero(ros, tmp_path):
    driver, calibrator, commander = turning_robot(ros, tmp_path, 'ground_destroy')
    moment = time.monotonic()
    ros.remove(calibrator)
    brought_to_rest(commander, driver, moment)
    remove_all(ros, commander, driver)


def test_refusals_say_why(ros, tmp_path):
    namespace = 'ground_refuse'
    calibrator = ros.calibrator(namespace, calibration_file=str(tmp_path / 'c.yaml'))
    commander = Commander(ros, namespace, calibrator=calibrator)
    refused = commander.call('mag_calibrator/rotate_and_calibrate')
    assert not refused.success and 'no input on /ground_refuse/imu/mag' in refused.message
    driver = sim_robot(ros, namespace)
    assert wait_for(lambda: accepted(calibrator) > 20)
    teleop = commander.create_publisher(Twist, 'cmd_vel', 10)
    assert wait_for(lambda: calibrator.count_publishers('/ground_refuse/cmd_vel') == 1)
    refused = commander.call('mag_calibrator/rotate_and_calibrate')
    assert not refused.success and 'other publisher' in refused.message
    commander.destroy_publisher(teleop)
    assert wait_for(lambda: calibrator.count_publishers('/ground_refuse/cmd_vel') == 0)
    assert commander.call('mag_calibrator/rotate_and_calibrate').success
    refused = commander.call('mag_calibrator/rotate_and_calibrate')
    assert not refused.success and 'already rotating' in refused.message
    assert calibrator._rotation.state == 'turning'
    moment = time.monotonic()
    assert commander.call('mag_calibrator/stop_rotation').success
    brought_to_rest(commander, driver, moment)
    remove_all(ros, commander, calibrator, driver)


def test_a_turn_restarted_after_cmd_vel_stamped_changed_commands_the_new_type(ros, tmp_path):
    """One participant cannot hold both types on one topic: each listener has its own context,
    as a base has its own process."""
    namespace = 'retyped'
    twist_side, stamped_side = Ros(), Ros()
    driver = calibrator = caller = None
    try:
        driver = ros.driver(namespace)
        calibrator = ros.calibrator(namespace, progress_log_period=0.0,
                                    calibration_file=str(tmp_path / 'c.yaml'))
        caller = ros.add(Node('caller', namespace=namespace, context=ros.context))
        twist_base = Commander(twist_side, namespace)
        stamped_base = Commander(stamped_side, namespace, stamped=True)
        assert wait_for(lambda: accepted(calibrator) > 20)
        assert call_trigger(caller, 'mag_calibrator/rotate_and_calibrate').success
        assert wait_for(lambda: (twist_base.last_twist() or 0.0) > 0.0)
        # The change stops the turn: its zero goes out as Twist, what the base listens to.
        ok, reason = set_parameter_over_service(caller, calibrator, 'cmd_vel_stamped', True)
        assert ok, reason
        assert calibrator._rotation.last_stop[0] == 'parameters'
        assert wait_for(lambda: twist_base.last_twist() == 0.0)
        # Restarted at once (within the zero hold): TwistStamped, as now asked.
        response = call_trigger(caller, 'mag_calibrator/rotate_and_calibrate')
        assert response.success, response.message
        assert wait_for(lambda: (stamped_base.last_twist() or 0.0) > 0.0), (
            'the restarted turn did not command TwistStamped')
        assert call_trigger(caller, 'mag_calibrator/stop_rotation').success
        assert wait_for(lambda: stamped_base.last_twist() == 0.0)
    finally:
        remove_all(ros, caller, calibrator, driver)  # the module's graph outlives this test
        twist_side.close()
        stamped_side.close()


def test_twist_stamped_for_nav2_style_bases(ros, tmp_path):
    """One process (DDS participant) cannot hold both types on one topic: the robot gets its
    own context here, as it has its own process on a robot."""
    namespace = 'ground_stamped'
    robot = Ros()
    try:
        driver = sim_robot(robot, namespace)
        calibrator = ros.calibrator(namespace, calibration_file=str(tmp_path / 'c.yaml'),
                                    cmd_vel_stamped=True, cmd_vel_frame_id='base_footprint')
        commander = Commander(ros, namespace, stamped=True, calibrator=calibrator)
        assert wait_for(lambda: accepted(calibrator) > 20)
        assert commander.call('mag_calibrator/rotate_and_calibrate').success
        assert wait_for(lambda: yaw_rate(driver) > 0.2), 'the sim did not follow TwistStamped'
        moment = time.monotonic()
        assert commander.call('mag_calibrator/stop_rotation').success
        brought_to_rest(commander, driver, moment)
        remove_all(ros, commander, calibrator)
    finally:
        robot.close()


# -- the process: Ctrl-C and SIGTERM --------------------------------------------------------------


def signalled_calibrator_process(ros: Ros, tmp_path: Path, stop_signal: signal.Signals) -> None:
    """A calibrator process turning a sim robot gets ``stop_signal``: it exits 0 and the robot
    is commanded to zero and comes to rest (AssertionError if not)."""
    namespace = f'ground_{stop_signal.name.lower()}'
    tmp_path.mkdir(exist_ok=True)
    driver = sim_robot(ros, namespace)
    commander = Commander(ros, namespace)
    process = subprocess.Popen(
        [sys.executable, '-m', 'mag_calibrator_ros.nodes.mag_calibrator', '--ros-args',
         '-r', f'__ns:=/{namespace}', '-p', f'calibration_file:={tmp_path / "c.yaml"}',
         '-p', 'progress_log_period:=0.0'],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        env=dict(os.environ), preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        started = None

        def rotating() -> bool:  # the process has just started: its answer may be lost
            nonlocal started
            started = try_trigger(commander, 'mag_calibrator/rotate_and_calibrate', 5.0)
            return ((started is not None and started.success)
                    or (commander.last_twist() or 0.0) > 0.0)

        assert wait_for(rotating, timeout_s=60.0, step_s=1.0), (
            'no answer' if started is None else started.message)
        assert wait_for(lambda: (commander.last_twist() or 0.0) > 0.2 and yaw_rate(driver) > 0.2)
        moment = time.monotonic()
        process.send_signal(stop_signal)
        output = process.communicate(timeout=30.0)[0].decode(errors='replace')
        assert process.returncode == 0, output
        assert 'the node is shutting down' in output, output
        exited = time.monotonic()
        brought_to_rest(commander, driver, moment)
        time.sleep(0.5)  # anything still on its way arrives
        assert commander.last_twist() == 0.0
        assert all(z == 0.0 for z in commander.twists_since(exited))
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    remove_all(ros, commander, driver)


def test_a_signalled_calibrator_process_leaves_the_robot_commanded_to_zero(ros, tmp_path):
    """SIGTERM and SIGINT, each to a process of its own turning a robot of its own (own
    namespaces), both at once: each mostly waits for its process to start."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        runs = {number.name: pool.submit(signalled_calibrator_process, ros, tmp_path / number.name,
                                         number)
                for number in (signal.SIGTERM, signal.SIGINT)}
    failures = [f'{name}: {run.exception()!r}' for name, run in runs.items() if run.exception()]
    assert not failures, '\n'.join(failures)
