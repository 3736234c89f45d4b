"""The calibrator node's small decisions without ROS: when auto_save writes, and where the
robot is for the World Magnetic Model (the parameters, else the first usable gps/fix)."""

from __future__ import annotations

import math

from sensor_msgs.msg import NavSatFix, NavSatStatus

from mag_calibrator_ros.nodes.auto_save import AUTO_SAVE_MIN_INTERVAL_S, AutoSaveThrottle
from mag_calibrator_ros.nodes.location import (
    fix_location,
    parameter_location,
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


def test_the_parameters_locate_unless_both_are_nan():
    assert parameter_location(NAN, NAN, 0.0) is None
    assert parameter_location(50.0, 14.4, 200.0) == (50.0, 14.4, 200.0)
    assert parameter_location_problems(NAN, NAN, 0.0) == []
    assert parameter_location_problems(50.0, NAN, 0.0) != []  # half a location is an error
    assert parameter_location_problems(95.0, 14.4, 0.0) != []


def test_a_fix_locates_only_when_usable_and_not_overridden():
    assert fix_location(fix(50.0, 14.4), True, NAN, NAN) == (50.0, 14.4, 100.0)
    assert fix_location(fix(50.0, 14.4, altitude=NAN), True, NAN, NAN) == (50.0, 14.4, 0.0)
    assert fix_location(fix(50.0, 14.4), False, NAN, NAN) is None  # use_gps off
    assert fix_location(fix(50.0, 14.4), True, 48.0, 11.0) is None  # the parameters win
    no_fix = fix(50.0, 14.4, status=NavSatStatus.STATUS_NO_FIX)
    assert fix_location(no_fix, True, NAN, NAN) is None
    assert fix_location(fix(NAN, 14.4), True, NAN, NAN) is None  # no position
