# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator with an IMU and a location over real rclpy/DDS: the simulated driver publishes
imu/mag and imu/data_raw from a misaligned magnetometer held still at one tilt after another; the
calibrator pairs them and knows the World Magnetic Model at its latitude/longitude or at a
gps/fix. What it then decides (aligned to the IMU, checked against the model) is replayed in
test_calibrator_replays.py."""

from __future__ import annotations

import math

from diagnostic_msgs.msg import DiagnosticStatus
from node_helpers import WAIT_S, Probe, wait_for
import pytest
from rclpy.node import Node
from sensor_msgs.msg import NavSatFix, NavSatStatus
from test_calibrator_node import HARD_IRON_UT, SOFT_IRON

from mag_calibrator_ros.calibration.fit.earth_field import earth_field

BERLIN = (52.52, 13.40, 34.0)
MISALIGNMENT_DEG = [1.8, -1.9, 1.4]  # 3.0 deg


def values_of(status: DiagnosticStatus) -> dict[str, str]:
    return {pair.key: pair.value for pair in status.values}


def test_the_imu_and_a_location_from_parameters_reach_the_calibration(ros, tmp_path):
    """The driver's imu/data_raw pairs with imu/mag, the location from the parameters gives the
    World Magnetic Model's field there, and /diagnostics says both. (That the calibration is
    then aligned to the IMU and sized by the model, and the corrected field the true one in the
    IMU frame: test_calibrator_replays.py, the same board replayed.)"""
    namespace = 'aligned'
    driver = ros.driver(namespace, **{
        'sim.hard_iron_ut': HARD_IRON_UT, 'sim.soft_iron': SOFT_IRON, 'sim.noise_ut': 0.3,
        'sim.motion': 'poses', 'sim.seed': 4, 'sim.mag_misalignment_deg': MISALIGNMENT_DEG,
        'sim.latitude': BERLIN[0], 'sim.longitude': BERLIN[1], 'sim.altitude': BERLIN[2]})
    calibrator = ros.calibrator(
        namespace, auto_calibrate=False, progress_log_period=0.0,
        calibration_file=str(tmp_path / 'calibration.yaml'),
        latitude=BERLIN[0], longitude=BERLIN[1], altitude=BERLIN[2])
    probe = Probe(ros, namespace)
    try:
        session = calibrator.session
        model = earth_field(*BERLIN)
        assert wait_for(lambda: session.report().imu.paired >= 200
                        and session.report().earth is not None, timeout_s=60.0), (
            session.report().imu)
        report = session.report()
        assert report.earth.declination_deg == pytest.approx(model.declination_deg)
        decided = report.counts.accepted - report.imu.waiting
        assert report.imu.paired > 0.9 * decided  # the driver's 225 Hz IMU: every reading pairs

        def located(status: DiagnosticStatus) -> bool:
            values = values_of(status)
            return 'declination_deg' in values and float(values.get('imu_rate_hz', 0)) > 0.0

        assert wait_for(lambda: any(located(s) for s in
                                    probe.statuses('mag_calibrator: calibration')))
        status = [s for s in probe.statuses('mag_calibrator: calibration') if located(s)][-1]
        values = values_of(status)
        assert values['location_source'] == 'parameters'
        assert float(values['declination_deg']) == pytest.approx(model.declination_deg, abs=0.01)
        assert float(values['model_intensity_uT']) == pytest.approx(
            model.intensity_nt / 1000.0, abs=0.01)
        assert int(values['readings_paired']) > 0
        # how late this node handles each stream, from the MessageInfo rclpy hands the
        # callbacks (issue #46 item 7: a late IMU is told apart from another clock)
        for key in ('imu_handled_after_s', 'mag_handled_after_s'):
            assert 0.0 <= float(values[key]) < math.inf, (key, values.get(key))
    finally:
        for node in (probe, calibrator, driver):
            ros.remove(node)


def test_a_gps_fix_locates_the_calibrator_and_use_imu_false_ignores_the_imu(ros):
    namespace = 'located'
    driver = ros.driver(namespace, **{'sim.motion': 'poses'})
    calibrator = ros.calibrator(namespace, auto_calibrate=False, progress_log_period=0.0,
                                use_imu=False)
    gps = ros.add(Node('gps', namespace=namespace, context=ros.context))
    publisher = gps.create_publisher(NavSatFix, 'gps/fix', 10)
    try:
        session = calibrator.session
        assert wait_for(lambda: session.report().counts.accepted > 50)
        imu = session.report().imu
        assert imu.accepted == 0 and imu.paired == 0
        assert wait_for(lambda: publisher.get_subscription_count() >= 1)
        fix = NavSatFix()
        fix.status.status = NavSatStatus.STATUS_NO_FIX
        fix.latitude, fix.longitude = 10.0, 10.0
        publisher.publish(fix)  # no fix: ignored
        fix.status.status = NavSatStatus.STATUS_FIX
        fix.latitude, fix.longitude, fix.altitude = -33.0, 109.0, math.nan
        for _ in range(3):
            publisher.publish(fix)
        assert wait_for(lambda: session.report().earth is not None, timeout_s=WAIT_S)
        earth = session.report().earth
        assert earth.latitude_deg == -33.0 and earth.altitude_m == 0.0
        assert earth.inclination_deg < -60.0  # the southern hemisphere's field points up
        fix.latitude = -33.01
        publisher.publish(fix)  # a fix 1 km away does not replace it (a far one does)
        assert not wait_for(lambda: session.report().earth.latitude_deg != -33.0,
                            timeout_s=1.0)
    finally:
        for node in (gps, calibrator, driver):
            ros.remove(node)


@pytest.mark.parametrize(('parameters', 'message'), [
    ({'latitude': 95.0, 'longitude': 0.0}, 'latitude must be within'),
    ({'latitude': 52.0}, 'longitude must be within'),
    ({'max_alignment_deg': 200.0}, 'max_alignment_deg'),
])
def test_a_bad_location_or_tolerance_refuses_to_start(ros, parameters, message):
    from rclpy.parameter import Parameter

    from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode
    from mag_calibrator_ros.nodes.parameters import ConfigurationError

    overrides = [Parameter(name, value=value) for name, value in parameters.items()]
    with pytest.raises(ConfigurationError, match=message):
        MagCalibratorNode(namespace='refused', context=ros.context,
                          parameter_overrides=overrides)
