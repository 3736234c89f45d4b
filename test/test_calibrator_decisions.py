# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibrator node's small decisions without ROS: when auto_save writes, and where the
robot is for the World Magnetic Model (the parameters, else a plausible gps/fix)."""

from __future__ import annotations

import math

import pytest
from sensor_msgs.msg import NavSatFix, NavSatStatus

from mag_calibrator_ros.nodes.auto_save import AUTO_SAVE_MIN_INTERVAL_S, AutoSaveThrottle
from mag_calibrator_ros.nodes.location import (
    FIX_MOVE_M,
    MAX_FIX_SD_M,
    LocationSource,
    distance_m,
    fix_refusal,
    parameter_location_problems,
)

NAN = math.nan


def test_auto_save_writes_once_at_a_time_and_at_most_every_interval():
    throttle = AutoSaveThrottle()
    assert not throttle.start(0.0)  # nothing adopted yet
    throttle.adopted(False)
    assert not throttle.start(0.0)  # auto_save off
    throttle.adopted(True)
    assert throttle.start(0.0)
    throttle.adopted(True)  # adopted while writing: written afterwards
    assert not throttle.start(AUTO_SAVE_MIN_INTERVAL_S + 1.0)
    throttle.finished()
    assert not throttle.start(AUTO_SAVE_MIN_INTERVAL_S - 0.1)  # too soon after the last write
    assert throttle.start(AUTO_SAVE_MIN_INTERVAL_S)
    throttle.finished()
    assert not throttle.start(100.0)  # nothing new adopted


def test_auto_save_turned_off_before_the_write_forgets_it():
    throttle = AutoSaveThrottle()
    throttle.adopted(True)
    throttle.adopted(False)
    assert not throttle.start(0.0)


def fix(latitude: float, longitude: float, altitude: float = 100.0,
        status: int = NavSatStatus.STATUS_FIX) -> NavSatFix:
    message = NavSatFix(latitude=latitude, longitude=longitude, altitude=altitude)
    message.status.status = status
    return message


def test_half_a_location_is_refused_at_start_up_and_waits_at_run_time():
    assert parameter_location_problems(NAN, NAN, 0.0) == []
    assert parameter_location_problems(50.0, NAN, 0.0) != []  # start-up: nothing completes it
    assert parameter_location_problems(50.0, NAN, 0.0, incomplete_ok=True) == []
    assert parameter_location_problems(NAN, 14.4, 0.0, incomplete_ok=True) == []
    assert parameter_location_problems(95.0, NAN, 0.0, incomplete_ok=True) != []
    assert parameter_location_problems(95.0, 14.4, 0.0) != []


def test_implausible_fixes_are_refused_with_their_reason():
    assert fix_refusal(fix(50.0, 14.4)) is None
    assert fix_refusal(fix(50.0, 14.4, altitude=NAN)) is None  # an unknown altitude is fine
    assert fix_refusal(fix(50.0, 14.4, status=NavSatStatus.STATUS_NO_FIX)) == 'no fix'
    assert fix_refusal(fix(NAN, 14.4)) == 'no position'
    assert fix_refusal(fix(50.0, math.inf)) == 'no position'
    assert fix_refusal(fix(95.0, 14.4)) == 'out of range'
    assert fix_refusal(fix(50.0, 14.4, altitude=2e6)) == 'out of range'
    assert fix_refusal(fix(0.0, 0.0, altitude=NAN)) == 'null island'
    assert fix_refusal(fix(0.0, 0.0, altitude=0.0)) == 'null island'
    assert fix_refusal(fix(0.0, 0.0, altitude=12.0)) is None  # a receiver that knows its height
    uncertain = fix(50.0, 14.4)
    uncertain.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    uncertain.position_covariance[0] = uncertain.position_covariance[4] = 25.0
    assert fix_refusal(uncertain) is None
    uncertain.position_covariance[4] = (2 * MAX_FIX_SD_M) ** 2
    assert fix_refusal(uncertain) == 'uncertain'
    uncertain.position_covariance[4] = NAN
    assert fix_refusal(uncertain) == 'uncertain'


def test_a_fix_locates_and_only_a_far_one_replaces_it():
    source = LocationSource()
    assert source.wanted is None
    assert source.offer_fix(fix(0.0, 0.0, altitude=NAN)) == 'null island'
    assert source.offer_fix(fix(0.0, 0.0, altitude=NAN)) == 'null island'
    assert source.offer_fix(fix(50.0, 14.4, status=-1)) == 'no fix'
    assert source.wanted is None and source.refused_text() == 'null island: 2, no fix: 1'
    assert source.offer_fix(fix(50.0, 14.4, altitude=NAN)) is None
    assert source.wanted == ((50.0, 14.4, 0.0), 'gps/fix')
    near = 50.0 + 0.8 * FIX_MOVE_M / 111_195.0  # a degree of latitude is 111.2 km
    source.offer_fix(fix(near, 14.4))
    assert source.wanted == ((50.0, 14.4, 0.0), 'gps/fix')  # hysteresis: not every fix
    far = 50.0 + 1.2 * FIX_MOVE_M / 111_195.0
    source.offer_fix(fix(far, 14.4))
    assert source.wanted == ((far, 14.4, 100.0), 'gps/fix')
    assert source.forget_fix() and source.wanted is None and not source.forget_fix()
    source.use_gps = False
    assert source.offer_fix(fix(48.0, 11.0)) is None and source.wanted is None


def test_the_parameters_win_wait_for_their_pair_and_hand_back_to_the_fix():
    source = LocationSource()
    source.offer_fix(fix(48.0, 11.0))
    source.set_parameters(52.5, NAN, 0.0)  # half a pair: waits, the fix stays in force
    assert 'waiting for longitude' in source.waiting
    assert source.wanted == ((48.0, 11.0, 100.0), 'gps/fix')
    source.set_parameters(52.5, 13.4, 34.0)
    assert source.wanted == ((52.5, 13.4, 34.0), 'parameters') and source.waiting == ''
    source.offer_fix(fix(10.0, 10.0))  # still followed, not in force
    assert source.wanted[1] == 'parameters' and source.fix == (10.0, 10.0, 100.0)
    source.set_parameters(NAN, 13.4, 34.0)  # clearing one at a time: the pair stays meanwhile
    assert 'waiting for latitude' in source.waiting
    assert source.wanted == ((52.5, 13.4, 34.0), 'parameters')
    source.set_parameters(NAN, NAN, 34.0)
    assert source.wanted == ((10.0, 10.0, 100.0), 'gps/fix') and source.waiting == ''


def test_distances_between_fixes():
    assert distance_m((0.0, 0.0, 0.0), (0.0, 1.0, 0.0)) == pytest.approx(111_195.0, rel=1e-4)
    assert distance_m((52.5, 13.4, 0.0), (52.5, 13.4, 900.0)) == 0.0  # altitude ignored
    assert distance_m((0.0, 179.9, 0.0), (0.0, -179.9, 0.0)) == pytest.approx(22_239.0, rel=1e-3)
