# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Where the calibrator's location comes from, over real rclpy/DDS: gps/fix screened, replaced
when far, forgotten on ~/reset, overridden by latitude/longitude, which are set one at a time
(ros2 param set), atomically, or from a file (ros2 param load), and cleared."""

from __future__ import annotations

import math
import textwrap

from diagnostic_msgs.msg import DiagnosticStatus
from node_helpers import Probe, call_trigger, set_parameter_over_service, wait_for
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from sensor_msgs.msg import NavSatFix, NavSatStatus


def values_of(status: DiagnosticStatus) -> dict[str, str]:
    return {pair.key: pair.value for pair in status.values}


def latest_values(probe: Probe, node: Node) -> dict[str, str]:
    statuses = probe.statuses_of(node)
    return values_of(statuses[-1]) if statuses else {}


def earth_latitude(node) -> float | None:
    earth = node.session.report().earth
    return None if earth is None else earth.latitude_deg


def a_fix(latitude: float, longitude: float, altitude: float = math.nan,
          status: int = NavSatStatus.STATUS_FIX) -> NavSatFix:
    fix = NavSatFix(latitude=latitude, longitude=longitude, altitude=altitude)
    fix.status.status = status
    return fix


def test_gps_fixes_are_screened_replaced_when_far_forgotten_on_reset_and_overridden(
        ros, tmp_path):
    namespace = 'fixes'
    calibrator = ros.calibrator(namespace, progress_log_period=0.0,
                                calibration_file=str(tmp_path / 'c.yaml'))
    probe = Probe(ros, namespace)
    gps = ros.add(Node('gps', namespace=namespace, context=ros.context))
    publisher = gps.create_publisher(NavSatFix, 'gps/fix', 10)
    try:
        assert wait_for(lambda: publisher.get_subscription_count() >= 1)
        # A receiver without a fix that still says STATUS_FIX: "null island", refused and counted.
        for _ in range(3):
            publisher.publish(a_fix(0.0, 0.0))
        publisher.publish(a_fix(10.0, 10.0, status=NavSatStatus.STATUS_NO_FIX))
        assert wait_for(lambda: 'null island' in latest_values(probe, calibrator).get(
            'gps_fixes_refused', '')), 'the null-island fix was not refused'
        assert calibrator.session.report().earth is None
        publisher.publish(a_fix(-33.0, 109.0))
        assert wait_for(lambda: earth_latitude(calibrator) is not None)
        assert earth_latitude(calibrator) == -33.0  # not 0.0: the bad fix did not stick
        # A good fix far from the one in force replaces it (a near one would not: unit tests).
        publisher.publish(a_fix(52.0, 13.4, 40.0))
        assert wait_for(lambda: earth_latitude(calibrator) == 52.0)
        assert calibrator.session.report().earth.altitude_m == 40.0
        # ~/reset forgets a fix's location; the next plausible fix locates again.
        response = call_trigger(probe, 'mag_calibrator/reset')
        assert response.success and 'gps/fix is forgotten' in response.message
        assert wait_for(lambda: calibrator.session.report().earth is None)
        publisher.publish(a_fix(48.0, 11.0))
        assert wait_for(lambda: earth_latitude(calibrator) == 48.0)
        # The parameters override fixes; clearing them hands back to the fixes.
        for name, value in (('latitude', 45.5), ('longitude', -122.7)):
            assert set_parameter_over_service(probe, calibrator, name, value)[0]
        assert wait_for(lambda: earth_latitude(calibrator) == 45.5)
        assert wait_for(lambda: (publisher.publish(a_fix(10.0, 10.0)),
                                 calibrator._earth_here.source.fix == (10.0, 10.0, 0.0))[1])
        assert calibrator._earth_here.asked[1] == 'parameters'  # the fix did not take over
        assert calibrator.session.report().earth.latitude_deg == 45.5
        for name in ('latitude', 'longitude'):
            assert set_parameter_over_service(probe, calibrator, name, math.nan)[0]
        assert wait_for(lambda: earth_latitude(calibrator) == 10.0)
        assert wait_for(lambda: latest_values(probe, calibrator).get('location_source')
                        == 'gps/fix')
    finally:
        for node in (gps, probe, calibrator):
            ros.remove(node)


def parameter_results(future) -> list[tuple[bool, str]]:
    """(successful, reason) of each parameter of a SetParameters(Atomically) answer."""
    assert wait_for(future.done)
    answer = future.result()
    results = answer.results if hasattr(answer, 'results') else [answer.result]
    return [(result.successful, result.reason) for result in results]


def test_latitude_and_longitude_set_one_at_a_time_atomically_from_a_file_and_cleared(
        ros, tmp_path):
    namespace = 'place'
    calibrator = ros.calibrator(namespace, progress_log_period=0.0, use_gps=False,
                                calibration_file=str(tmp_path / 'c.yaml'))
    probe = Probe(ros, namespace)
    client = AsyncParameterClient(probe, calibrator.get_fully_qualified_name())
    try:
        assert client.wait_for_services(timeout_sec=20.0)
        # ros2 param set, one after the other: the first waits for the second.
        ok, reason = set_parameter_over_service(probe, calibrator, 'latitude', 52.52)
        assert ok, reason
        assert wait_for(lambda: 'waiting for longitude' in latest_values(probe, calibrator).get(
            'location_waiting', ''))
        assert calibrator.session.report().earth is None
        ok, reason = set_parameter_over_service(probe, calibrator, 'longitude', 13.40)
        assert ok, reason
        assert wait_for(lambda: earth_latitude(calibrator) == 52.52)
        assert wait_for(lambda: 'location_waiting' not in latest_values(probe, calibrator))
        # Atomically (SetParametersAtomically).
        future = client.set_parameters_atomically(
            [Parameter('latitude', value=48.1), Parameter('longitude', value=11.6)])
        assert all(ok for ok, _ in parameter_results(future))
        assert wait_for(lambda: earth_latitude(calibrator) == 48.1)
        # ros2 param load: both in one SetParameters request, set one at a time.
        params_file = tmp_path / 'place.yaml'
        params_file.write_text(textwrap.dedent(f"""\
            {calibrator.get_fully_qualified_name()}:
              ros__parameters:
                longitude: -122.7
                latitude: 45.5
            """))
        assert all(ok for ok, _ in parameter_results(client.load_parameter_file(
            str(params_file))))
        assert wait_for(lambda: earth_latitude(calibrator) == 45.5)
        assert calibrator.session.report().earth.longitude_deg == -122.7
        # A bad value alone is still refused, with the reason.
        ok, reason = set_parameter_over_service(probe, calibrator, 'latitude', 95.0)
        assert not ok and 'latitude must be within' in reason
        # Cleared one at a time: the location stays until both are NaN, then there is none.
        assert set_parameter_over_service(probe, calibrator, 'latitude', math.nan)[0]
        assert wait_for(lambda: 'waiting for latitude' in latest_values(probe, calibrator).get(
            'location_waiting', ''))
        assert calibrator.session.report().earth.latitude_deg == 45.5
        assert set_parameter_over_service(probe, calibrator, 'longitude', math.nan)[0]
        assert wait_for(lambda: calibrator.session.report().earth is None)
    finally:
        for node in (probe, calibrator):
            ros.remove(node)
