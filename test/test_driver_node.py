"""icm20948_driver over real rclpy/DDS with the simulated chip: output, faults, parameters."""

import math
import os
from pathlib import Path
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import MagneticField

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.nodes.icm20948_driver import (
    DriverConfigurationError,
    Icm20948DriverNode,
)


@pytest.fixture(scope='module', autouse=True)
def ros():
    owner = not rclpy.ok()  # another module may already hold the default context
    if owner:
        rclpy.init()
    yield
    if owner:
        rclpy.try_shutdown()


class Harness:
    """A driver node plus a listener node on one executor, spun from the test thread."""

    def __init__(self, namespace: str = 'robot', **parameters) -> None:
        overrides = [Parameter('backend', value='sim')]
        overrides += [Parameter(name.replace('__', '.'), value=value)
                      for name, value in parameters.items()]
        self.node = Icm20948DriverNode(namespace=namespace, parameter_overrides=overrides)
        self.listener = rclpy.create_node('listener', namespace=namespace)
        self.messages: list[tuple[float, MagneticField]] = []
        self.statuses: list[DiagnosticStatus] = []
        # Consumers subscribe with sensor-data QoS (REP-2003): must match a reliable publisher.
        self.listener.create_subscription(
            MagneticField, 'imu/mag',
            lambda m: self.messages.append((time.monotonic(), m)), qos_profile_sensor_data,
        )
        self.listener.create_subscription(
            DiagnosticArray, '/diagnostics', lambda a: self.statuses.extend(a.status), 10
        )
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.listener)

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)

    def spin_until(self, condition, limit_s: float = 10.0) -> bool:
        end = time.monotonic() + limit_s
        while time.monotonic() < end:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return condition()

    def stamps(self) -> np.ndarray:
        return np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
                         for _, m in self.messages])

    def fields(self) -> np.ndarray:
        return np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z]
                         for _, m in self.messages])

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.listener.destroy_node()


@pytest.fixture
def harness_factory():
    made = []

    def factory(**kwargs) -> Harness:
        made.append(Harness(**kwargs))
        return made[-1]

    yield factory
    for harness in made:
        harness.close()


def assert_valid_stream(harness: Harness) -> None:
    stamps = harness.stamps()
    assert np.all(np.diff(stamps) > 0), 'stamps must strictly increase'
    fields = harness.fields()
    assert np.all(np.isfinite(fields))
    assert np.all(np.any(np.diff(fields, axis=0) != 0, axis=1)), 'a sample was published twice'


def test_publishes_tesla_in_the_chip_frame_with_covariance(harness_factory):
    h = harness_factory(frame_id='mag_test_link', magnetic_field_stddev=4e-7, sim__seed=3)
    assert h.spin_until(lambda: len(h.messages) >= 100)
    assert_valid_stream(h)
    fields = h.fields()
    np.testing.assert_allclose(np.linalg.norm(fields, axis=1), 50e-6, atol=3e-6)  # tesla
    for _, message in h.messages:
        assert message.header.frame_id == 'mag_test_link'
        np.testing.assert_allclose(message.magnetic_field_covariance,
                                   [1.6e-13, 0, 0, 0, 1.6e-13, 0, 0, 0, 1.6e-13])
    # Each published vector is the simulator's chip-frame truth plus noise and quantisation.
    truths = np.array([h.node.simulator.truth_for_reading(f) for f in fields])
    assert np.max(np.linalg.norm(fields - truths, axis=1)) < 3e-6
    publishers = h.listener.get_publisher_names_and_types_by_node('icm20948_driver', '/robot')
    assert ('/robot/imu/mag', ['sensor_msgs/msg/MagneticField']) in publishers  # relative name


def test_unknown_covariance_is_all_zeros_never_minus_one(harness_factory):
    h = harness_factory(sim__motion='yaw')
    assert h.spin_until(lambda: len(h.messages) >= 10)
    for _, message in h.messages:
        assert list(message.magnetic_field_covariance) == [0.0] * 9
        assert message.header.frame_id == 'imu_link'


def test_rate_parameter_paces_the_stream(harness_factory):
    h = harness_factory(rate_hz=10, sim__motion='still', sim__noise_ut=0.0)
    h.spin(1.5)
    # Not a timing assertion: 1.5 s at 10 Hz cannot hold more than 16 samples, at 100 Hz it would.
    assert 0 < len(h.messages) <= 16
    assert h.node.settings.rate_hz == 10


def test_diagnostics_report_rate_counters_bus_and_address(harness_factory):
    h = harness_factory(address=0x68)
    assert h.spin_until(lambda: any(s.hardware_id for s in h.statuses), limit_s=5.0)
    status = h.statuses[-1]
    values = {kv.key: kv.value for kv in status.values}
    assert status.name == 'icm20948_driver: magnetometer'
    assert status.hardware_id == 'icm20948@sim:0x68'
    assert values['bus'] == 'sim' and values['address'] == '0x68'
    for key in ('measured rate (Hz)', 'i2c errors', 'overflows (HOFL)', 'overruns (DOR)',
                'reinitialisations', 'published'):
        assert key in values
    assert status.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN)


def test_survives_i2c_errors_and_publishes_only_valid_samples(harness_factory):
    h = harness_factory(sim__i2c_error_rate=0.05, sim__seed=5)
    h.spin(3.0)
    assert h.node.i2c_errors > 0
    assert len(h.messages) > 0
    assert_valid_stream(h)
    np.testing.assert_allclose(np.linalg.norm(h.fields(), axis=1), 50e-6, atol=3e-6)
    before = h.node.published
    assert h.spin_until(lambda: h.node.published > before + 10)  # still alive and publishing
    assert any(s.level == DiagnosticStatus.WARN and 'I2C errors' in s.message
               for s in h.statuses)


def test_overflowed_samples_are_never_published(harness_factory):
    # 4900 uT of hard iron + the earth field: many samples beyond the AK09916's +-4912.8 uT.
    h = harness_factory(sim__hard_iron_ut=[4900.0, 0.0, 0.0], sim__field_ut=50.0, sim__seed=2)
    assert h.spin_until(lambda: h.node.overflows > 10 and len(h.messages) > 10)
    assert np.all(np.abs(h.fields()) <= 32752 * 0.15e-6 + 1e-12)
    assert_valid_stream(h)
    assert h.spin_until(lambda: any(
        {kv.key: kv.value for kv in s.values}.get('overflows (HOFL)', '0') != '0'
        for s in h.statuses
    ), limit_s=5.0)


def test_outage_stops_output_then_recovers(harness_factory):
    h = harness_factory(sim__seed=6)
    assert h.spin_until(lambda: len(h.messages) >= 20)
    clock = h.node.get_clock()
    outage_start = clock.now().nanoseconds * 1e-9
    h.node.simulator.start_outage(1.5)  # > 1 s, so a 1 Hz diagnostics tick falls inside it
    outage_end = outage_start + 1.5
    h.spin(1.5)
    assert h.spin_until(lambda: h.node.reinitialisations >= 1 and
                        h.stamps()[-1] > outage_end, limit_s=10.0)
    stamps = h.stamps()
    assert not np.any((stamps > outage_start) & (stamps < outage_end)), 'published in an outage'
    assert_valid_stream(h)
    assert any(s.level == DiagnosticStatus.ERROR for s in h.statuses)
    assert h.node.last_recovery_s is not None and h.node.last_recovery_s > 0.0


def test_chip_reset_is_detected_and_recovered(harness_factory):
    h = harness_factory(sim__seed=7)
    assert h.spin_until(lambda: len(h.messages) >= 10)
    h.node.simulator.chip_reset()
    count = len(h.messages)
    assert h.spin_until(lambda: h.node.reinitialisations >= 1 and len(h.messages) > count + 10)
    assert_valid_stream(h)


def test_stuck_data_ready_is_detected_and_recovered(harness_factory):
    h = harness_factory(sim__seed=8)
    assert h.spin_until(lambda: len(h.messages) >= 10)
    # Only the magnetometer resets (back to power-down): no bus error, DRDY simply never comes.
    h.node.simulator.write_byte_data(reg.AK09916_ADDRESS, reg.CNTL3, reg.CNTL3_SRST)
    count = len(h.messages)
    assert h.spin_until(lambda: h.node.reinitialisations >= 1 and len(h.messages) > count + 10)
    assert 'CNTL2' in h.node._last_error
    assert_valid_stream(h)


def test_missing_i2c_bus_keeps_the_node_alive_with_an_error(harness_factory):
    h = harness_factory(backend='smbus2', i2c_bus=250)
    assert h.spin_until(
        lambda: any(s.level == DiagnosticStatus.ERROR for s in h.statuses), limit_s=5.0
    )
    status = [s for s in h.statuses if s.level == DiagnosticStatus.ERROR][-1]
    assert '/dev/i2c-250' in status.message
    assert h.messages == []
    assert h.node.simulator is None


@pytest.mark.parametrize('overrides, fragment', [
    ({'rate_hz': 30}, 'rate_hz must be one of [10, 20, 50, 100]'),
    ({'rate_hz': 200}, 'rate_hz'),
    ({'backend': 'spidev'}, 'backend must be one of smbus2, sim'),
    ({'address': 0x0C}, 'address'),
    ({'frame_id': '/imu_link'}, 'frame_id must not start with a slash'),
    ({'frame_id': ''}, 'frame_id must be a non-empty string'),
    ({'magnetic_field_stddev': -1.0}, 'magnetic_field_stddev'),
    ({'sim.motion': 'shake'}, 'sim.motion must be one of tumble, yaw, still'),
    ({'sim.soft_iron': [1.0, 0.2, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}, 'symmetric'),
    ({'sim.hard_iron_ut': [1.0, 2.0]}, 'hard_iron_ut must be 3 finite numbers'),
    ({'sim.hard_iron_ut': [1, 2, 3]}, 'expected list of 3 doubles'),
    ({'sim.i2c_error_rate': 1.0}, 'sim.i2c_error_rate'),
])
def test_invalid_parameters_are_refused_with_a_reason(overrides, fragment):
    parameters = [Parameter('backend', value='sim')]
    parameters += [Parameter(name, value=value) for name, value in overrides.items()]
    with pytest.raises(DriverConfigurationError) as caught:
        Icm20948DriverNode(parameter_overrides=parameters)
    assert fragment in str(caught.value)


def test_runtime_parameter_changes_are_validated(harness_factory):
    h = harness_factory()
    node = h.node
    results = node.set_parameters([Parameter('frame_id', value='')])
    assert not results[0].successful and 'frame_id' in results[0].reason
    assert not node.set_parameters([Parameter('rate_hz', value=50)])[0].successful  # read-only
    assert not node.set_parameters(
        [Parameter('magnetic_field_stddev', value=math.nan)]
    )[0].successful
    assert node.set_parameters([Parameter('frame_id', value='imu_2')])[0].successful
    assert node.set_parameters([Parameter('magnetic_field_stddev', value=1e-6)])[0].successful
    h.messages.clear()
    assert h.spin_until(lambda: len(h.messages) >= 5)
    message = h.messages[-1][1]
    assert message.header.frame_id == 'imu_2'
    assert message.magnetic_field_covariance[4] == pytest.approx(1e-12)


def test_console_script_exits_non_zero_on_invalid_parameters():
    script = Path(sys.executable).with_name('icm20948_driver')
    command = [str(script)] if script.exists() else [
        sys.executable, '-m', 'mag_calibrator_ros.nodes.icm20948_driver'
    ]
    result = subprocess.run(
        command + ['--ros-args', '-p', 'backend:=sim', '-p', 'rate_hz:=30'],
        capture_output=True, text=True, timeout=30, env=dict(os.environ),
    )
    assert result.returncode == 2
    assert 'rate_hz must be one of' in result.stdout + result.stderr


def test_shipped_params_file_loads_and_matches_the_defaults(tmp_path):
    """config/icm20948_driver.yaml documents the defaults: it must parse and agree with them."""
    import yaml

    from mag_calibrator_ros.nodes.icm20948_driver import PARAMETERS

    path = Path(__file__).resolve().parents[1] / 'config' / 'icm20948_driver.yaml'
    documented = yaml.safe_load(path.read_text())['icm20948_driver']['ros__parameters']
    assert set(documented) == set(PARAMETERS)
    for name, (default, _) in PARAMETERS.items():
        assert documented[name] == default and type(documented[name]) is type(default), name
    # The file really reaches the node: an edited copy changes what the node runs with.
    edited = tmp_path / 'driver.yaml'
    edited.write_text(path.read_text().replace('rate_hz: 100', 'rate_hz: 20')
                      .replace('backend: smbus2', 'backend: sim'))
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '--params-file', str(edited)], context=context)
    try:
        node = Icm20948DriverNode(context=context)
        assert node.settings.rate_hz == 20 and node.simulator is not None
        assert node.get_parameter('sim.soft_iron').value == list(PARAMETERS['sim.soft_iron'][0])
        assert node.get_parameter('address').value == 0x69
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
