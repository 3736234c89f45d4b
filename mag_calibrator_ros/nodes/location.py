"""Where the robot is, for the World Magnetic Model: the ``latitude``/``longitude`` parameters,
else the first usable fix on ``gps/fix``.

The parameters win: a user who set them knows better than a receiver that may not have settled.
A fix is evaluated once, whatever its outcome: the model's field barely changes over a robot's
range, and a fix stream would otherwise repeat the evaluation many times a second.
"""

from __future__ import annotations

import math

from sensor_msgs.msg import NavSatFix, NavSatStatus

from mag_calibrator_ros.calibration.fit.earth_field import location_problems

Location = tuple[float, float, float]
"""(latitude deg north, longitude deg east, altitude m above the WGS84 ellipsoid)."""
LOCATION_PARAMETERS = ('latitude', 'longitude', 'altitude')


def is_nan(value: object) -> bool:
    """A float NaN (the parameters' 'unknown'); anything else, even a bad type, is not."""
    return isinstance(value, float) and math.isnan(value)


def parameter_location_problems(latitude: object, longitude: object,
                                altitude: object) -> list[str]:
    """What is wrong with these parameter values; NaN and NaN (no location) is fine."""
    if is_nan(latitude) and is_nan(longitude):
        return []
    return location_problems(latitude, longitude, altitude)


def parameter_location(latitude: float, longitude: float, altitude: float) -> Location | None:
    """The location the parameters give; None when latitude and longitude are both NaN."""
    if math.isnan(latitude) and math.isnan(longitude):
        return None
    return latitude, longitude, altitude


def fix_location(fix: NavSatFix, use_gps: bool, latitude_parameter: object,
                 longitude_parameter: object) -> Location | None:
    """The location of ``fix`` when it should locate the robot: ``use_gps`` on, no location in
    the parameters, a real fix, and a valid position (an unknown altitude counts as 0 m)."""
    if (not use_gps or fix.status.status < NavSatStatus.STATUS_FIX
            or not (is_nan(latitude_parameter) and is_nan(longitude_parameter))):
        return None
    altitude = fix.altitude if math.isfinite(fix.altitude) else 0.0
    if location_problems(fix.latitude, fix.longitude, altitude):
        return None
    return fix.latitude, fix.longitude, altitude
