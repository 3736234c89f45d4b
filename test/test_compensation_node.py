# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibrator node learns the robot's own field over DDS: a battery current on
``battery_state`` (sensor_msgs/BatteryState) and the die temperature on ``imu/temperature``
(sensor_msgs/Temperature) beside ``imu/mag``, the compensation adopted on evidence and shown in
``/diagnostics``, ``calibration.*`` and the ``~/calibrate`` answer; ``~/learn_compensation``
answers by the node's own clock when no reading comes. Learning on request is replayed through
the session in test_compensation_replays.py."""

from __future__ import annotations

import subprocess
import sys
import time

from node_helpers import Probe, set_parameter_over_service, wait_for
import numpy as np
import pytest
from sensor_msgs.msg import BatteryState, Temperature
from std_srvs.srv import Trigger
from test_compensation import BATTERY, OFFSET, F, drive

from mag_calibrator_ros.calibration.live.inputs import parse_input

SECONDS = 100.0
RATE_HZ = 20.0


def _publish(probe: Probe, run: dict[str, np.ndarray], battery, temperature) -> None:
    """The course, stamped at its own rate, sent a little faster than real time."""
    for index, when in enumerate(run['t']):
        sec, nanosec = int(when), int(round((when % 1.0) * 1e9))
        current = BatteryState()
        current.header.stamp.sec, current.header.stamp.nanosec = sec, nanosec
        current.current = float(run['current'][index])
        battery.publish(current)
        if index % 4 == 0:
            die = Temperature()
            die.header.stamp.sec, die.header.stamp.nanosec = sec, nanosec
            die.temperature = float(run['temperature'][index])
            temperature.publish(die)
        probe.send(run['raw'][index], sec, nanosec)
        time.sleep(0.004)  # the calibrator keeps up (best-effort input, depth 100)


@pytest.fixture
def learning(ros):
    namespace = 'own_field'
    calibrator = ros.calibrator(
        namespace, auto_calibrate=False, refine=False, use_imu=False, progress_log_period=0.0,
        interference_inputs=[BATTERY],
        **{'calibration.offset': [float(v) for v in OFFSET + [0.8e-6 * 3.0, 0.0, 0.0]],
           'calibration.matrix': [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
           'calibration.field_strength': F, 'calibration.model': 'full'})
    probe = Probe(ros, namespace)
    battery = probe.create_publisher(BatteryState, parse_input(BATTERY).topic, 100)
    temperature = probe.create_publisher(Temperature, 'imu/temperature', 100)
    assert wait_for(lambda: probe.connected_to(calibrator)
                    and battery.get_subscription_count() >= 1
                    and temperature.get_subscription_count() >= 1)
    yield calibrator, probe, battery, temperature
    for node in (probe, calibrator):
        ros.remove(node)


def test_the_node_learns_a_battery_current_and_the_temperature_and_shows_them(learning):
    calibrator, probe, battery, temperature = learning
    run = drive(seconds=SECONDS, rate=RATE_HZ)
    _publish(probe, run, battery, temperature)
    session = calibrator.session
    assert wait_for(lambda: session.report().counts.adoptions.get('compensation', 0) >= 1,
                    timeout_s=60.0), (
        f'no compensation adopted: {session.report().compensation_needs}')
    # The wiring is judged here (inputs paired, a term adopted on evidence and shown); how
    # close the gain comes is the offline tests' and bench_interference's, since what a
    # best-effort subscription drops under load changes what there is to learn from.
    gain = session.calibration.compensation.interference[:, 0]
    assert 0.0 < gain[0] < 2 * 0.8e-6, gain
    assert wait_for(lambda: any(
        value.key == f'interference_uT_per_unit[{BATTERY}]'
        for status in probe.statuses_of(calibrator) for value in status.values))
    assert wait_for(lambda: calibrator.get_parameter('calibration.interference').value
                    is not None)
    shown = list(calibrator.get_parameter('calibration.interference').value)
    assert shown[0] > 0.0  # K[x, battery], in tesla per ampere
    assert calibrator.get_parameter('calibration.interference_inputs').value == [BATTERY]
    # The buffer kept its readings through the adoption, moved by the new compensation, so
    # a static fit needs no second drive.
    buffer = session.report().buffer
    assert buffer.fill == buffer.capacity
    answer = probe.call('mag_calibrator/calibrate')  # a static fit keeps the compensation
    assert answer.success and "compensating the robot's own field" in answer.message


def test_a_bad_interference_input_is_refused_with_its_form(learning):
    calibrator, probe, _, _ = learning
    ok, reason = set_parameter_over_service(probe, calibrator, 'interference_inputs',
                                            ['battery current'])
    assert not ok
    assert 'topic:package/msg/Type:field' in reason


def test_an_input_set_at_run_time_is_subscribed_in_that_change_and_rcl_names_are_checked(
        learning):
    """Issue #47: rclpy runs post-set callbacks newest first, and the inputs' own ran before the
    node's settings changed: a new input was subscribed one change late. A topic rcl refuses
    (``battery_c/``) passed the spec's pattern and killed the node at the next change."""
    calibrator, probe, _, _ = learning
    odometry = 'odom:nav_msgs/msg/Odometry:twist.twist.linear.x'
    assert set_parameter_over_service(probe, calibrator, 'interference_inputs',
                                      [BATTERY, odometry])[0]
    assert wait_for(lambda: probe.count_subscribers('/own_field/odom') >= 1), (
        'the new input was not subscribed by the change that set it')
    ok, reason = set_parameter_over_service(probe, calibrator, 'interference_inputs',
                                            ['battery_c/:sensor_msgs/msg/BatteryState:current'])
    assert not ok and 'must not end with a forward slash' in reason
    assert set_parameter_over_service(probe, calibrator, 'compensation_timeout', 30.0)[0]
    assert probe.call('mag_calibrator/reset').success  # alive after both
    assert calibrator.get_parameter('interference_inputs').value == [BATTERY, odometry]


def _ask(probe: Probe, service: str):
    """Call a Trigger service without waiting (the answer comes once readings taught it)."""
    client = probe.create_client(Trigger, service)
    assert client.wait_for_service(timeout_sec=20.0), f'{service} not available'
    return client.call_async(Trigger.Request())


def test_learn_compensation_without_readings_answers_by_the_nodes_own_clock(learning):
    calibrator, probe, _, _ = learning
    assert set_parameter_over_service(probe, calibrator, 'compensation_timeout', 5.0)[0]
    answer = _ask(probe, 'mag_calibrator/learn_compensation')
    assert wait_for(answer.done, timeout_s=40.0), 'no answer'
    response = answer.result()
    assert not response.success
    assert 'too few magnetometer readings arrived' in response.message

    def learning() -> bool:
        return 'compensation_learning' in calibrator.session.report().values

    assert not learning()  # the window closed: a new request learns again
    again = _ask(probe, 'mag_calibrator/learn_compensation')
    # A refusal ('already learning') answers at once; an accepted request opens the window.
    assert wait_for(lambda: again.done() or learning())
    assert not again.done() or 'already learning' not in again.result().message
    assert probe.call('mag_calibrator/reset').success  # it answers now, not in 12.5 s
    assert wait_for(again.done), 'no answer'
    assert not again.result().success
    assert again.result().message == '~/reset emptied what it was learning from'


def test_learn_compensation_with_no_input_configured_answers_at_once_naming_the_topics(ros):
    """With interference_inputs empty and no die temperature, ~/learn_compensation ran its full
    60 s and answered about the temperature, never that no input was configured, although
    battery_state was published (issue #46). It answers at once, naming the entry that would
    learn from the BatteryState topic it sees."""
    namespace = 'no_inputs'
    calibrator = ros.calibrator(
        namespace, auto_calibrate=False, refine=False, use_imu=False, progress_log_period=0.0,
        **{'calibration.offset': [float(v) for v in OFFSET],
           'calibration.matrix': [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
           'calibration.field_strength': F, 'calibration.model': 'full'})
    probe = Probe(ros, namespace)
    probe.create_publisher(BatteryState, 'battery_state', 10)
    entry = f'/{namespace}/battery_state:sensor_msgs/msg/BatteryState:current'
    assert wait_for(lambda: any(name == f'/{namespace}/battery_state' for name, _ in
                                calibrator.get_topic_names_and_types()))
    answer = _ask(probe, 'mag_calibrator/learn_compensation')
    assert wait_for(answer.done, timeout_s=10.0), 'no answer at once'
    response = answer.result()
    assert not response.success
    assert response.message.startswith('nothing to learn: interference_inputs is empty and no '
                                       'die temperature has come on imu/temperature')
    assert f"published now: interference_inputs:=['{entry}']" in response.message
    for node in (probe, calibrator):
        ros.remove(node)


def test_a_type_of_no_interface_package_runs_nothing_of_that_package():
    """Issue #47 item 6: an input spec's package was imported on the executor thread to find
    its message type, and 'matplotlib/msg/Figure' stalled the node 386 ms importing matplotlib.
    A package without rosidl's msg subpackage is refused before any of it runs."""
    code = ('import sys\n'
            'from mag_calibrator_ros.nodes.inputs import message_class\n'
            'try:\n'
            "    message_class('matplotlib/msg/Figure')\n"
            'except ImportError as error:\n'
            '    print(error)\n'
            "print('matplotlib' in sys.modules, message_class('sensor_msgs/msg/BatteryState')"
            '.__name__)\n')
    shown = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                           check=True, timeout=120).stdout.splitlines()
    assert shown == ["no ROS interface package 'matplotlib' (with a msg subpackage) is "
                     'installed', 'False BatteryState']
