"""mag_calibrator with an IMU and a location over real rclpy/DDS: the simulated driver publishes
imu/mag and imu/data_raw from a misaligned magnetometer held still at one tilt after another; the
calibrator pairs them, aligns the calibration to the IMU and checks it against the World Magnetic
Model at its latitude/longitude or at a gps/fix."""

from __future__ import annotations

import math

from diagnostic_msgs.msg import DiagnosticStatus
from node_helpers import WAIT_S, Probe, angle_deg, vector, wait_for
import numpy as np
import pytest
from rclpy.node import Node
from sensor_msgs.msg import NavSatFix, NavSatStatus
from test_calibrator_node import HARD_IRON_UT, SOFT_IRON

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.fit.earth_field import earth_field

BERLIN = (52.52, 13.40, 34.0)
MISALIGNMENT_DEG = [1.8, -1.9, 1.4]  # 3.0 deg


def values_of(status: DiagnosticStatus) -> dict[str, str]:
    return {pair.key: pair.value for pair in status.values}


def test_live_alignment_to_the_imu_with_the_world_magnetic_model(ros, tmp_path):
    namespace = 'aligned'
    driver = ros.driver(namespace, **{
        'sim.hard_iron_ut': HARD_IRON_UT, 'sim.soft_iron': SOFT_IRON, 'sim.noise_ut': 0.3,
        'sim.motion': 'poses', 'sim.seed': 4, 'sim.mag_misalignment_deg': MISALIGNMENT_DEG,
        'sim.latitude': BERLIN[0], 'sim.longitude': BERLIN[1], 'sim.altitude': BERLIN[2]})
    calibrator = ros.calibrator(
        namespace, auto_calibrate=False, progress_log_period=0.0, min_coverage=0.45,
        calibration_file=str(tmp_path / 'calibration.yaml'),
        latitude=BERLIN[0], longitude=BERLIN[1], altitude=BERLIN[2])
    probe = Probe(ros, namespace)
    try:
        session = calibrator.session
        findings = session.findings
        ready = wait_for(lambda: session.attitudes.fill >= 10 and findings.earth is not None
                         and session.buffer.coverage().fraction >= 0.5, timeout_s=90.0)
        assert ready, (f'not ready: {session.progress_text()}, {session.attitudes.fill} '
                       f'attitudes, paired {session.pairing.paired} of {session.accepted}')
        response = probe.call('mag_calibrator/calibrate')
        assert response.success, response.message
        assert 'aligned to the IMU' in response.message
        assert 'WMM2025' in response.message and 'declination' in response.message
        calibration = session.calibration
        truth = driver.simulator.board.mag_misalignment
        assert rotation_angle_deg(calibration.rotation @ truth.T) < 0.3
        model = earth_field(*BERLIN)
        assert calibration.field_strength == pytest.approx(model.intensity_nt * 1e-9)
        assert calibration.metadata['dip_deg'] == pytest.approx(model.inclination_deg, abs=0.3)
        assert session.pairing.paired > 0.9 * session.accepted  # 225 Hz IMU: every reading pairs
        # The corrected stream is the true field in the IMU frame.
        probe.take_corrected()
        assert wait_for(lambda: len(probe.corrected) >= 50)
        errors = []
        for msg in probe.take_corrected()[:50]:
            raw = probe.raw_for(msg)
            truth_t = driver.simulator.truth_for_reading(raw) if raw is not None else None
            if truth_t is not None:
                errors.append(angle_deg(vector(msg), truth_t))
        assert len(errors) >= 20 and np.sqrt(np.mean(np.square(errors))) < 1.0
        assert wait_for(lambda: any('dip_deg' in values_of(s) for s in
                                    probe.statuses('mag_calibrator: calibration')))
        status = [s for s in probe.statuses('mag_calibrator: calibration')
                  if 'dip_deg' in values_of(s)][-1]
        values = values_of(status)
        assert status.level == DiagnosticStatus.OK, status.message
        assert values['location_source'] == 'parameters'
        assert float(values['alignment_angle_deg']) == pytest.approx(3.0, abs=0.3)
        assert float(values['declination_deg']) == pytest.approx(model.declination_deg, abs=0.01)
        # the IMU's rate is reported; its value is the loaded machine's (21 of 225 Hz seen)
        assert float(values['imu_rate_hz']) > 0.0
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
        assert wait_for(lambda: session.accepted > 50)
        assert session.pairing.accepted == 0 and session.pairing.paired == 0
        assert wait_for(lambda: publisher.get_subscription_count() >= 1)
        fix = NavSatFix()
        fix.status.status = NavSatStatus.STATUS_NO_FIX
        fix.latitude, fix.longitude = 10.0, 10.0
        publisher.publish(fix)  # no fix: ignored
        fix.status.status = NavSatStatus.STATUS_FIX
        fix.latitude, fix.longitude, fix.altitude = -33.0, 109.0, math.nan
        for _ in range(3):
            publisher.publish(fix)
        findings = session.findings
        assert wait_for(lambda: findings.earth is not None, timeout_s=WAIT_S)
        assert findings.earth.latitude_deg == -33.0 and findings.earth.altitude_m == 0.0
        assert findings.earth.inclination_deg < -60.0  # the southern hemisphere's field points up
        fix.latitude = -33.01
        publisher.publish(fix)  # a fix 1 km away does not replace it (a far one does)
        assert not wait_for(lambda: findings.earth.latitude_deg != -33.0, timeout_s=1.0)
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
