# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Where the robot is, for the World Magnetic Model: the ``latitude``/``longitude`` parameters,
else a plausible fix on ``gps/fix``. :class:`LocationSource` decides; :class:`EarthFieldHere`
evaluates the model (on the node's I/O thread) whenever ``LocationSource.wanted`` changes and
hands the field to the session.

- The parameters win: a user who set both knows better than a receiver that may not have
  settled. Setting them to NaN hands the location back to the fixes.
- ``ros2 param set`` and ``ros2 param load`` set one parameter at a time, so one of the pair
  given and the other NaN is accepted as *incomplete*: it waits for the other, and the last
  complete pair (a location, or none: the fixes) stays in force meanwhile (diagnostics say so).
- A fix is screened first (``fix_refusal``): no fix, no position, out of range, "null island"
  (exactly 0, 0 with no altitude: a receiver reporting STATUS_FIX before it has one) or a
  reported uncertainty beyond MAX_FIX_SD_M is refused, each reason counted.
- The first plausible fix locates; a later one replaces it only when it is more than
  FIX_MOVE_M away (hysteresis: a fix stream does not re-evaluate the model many times a second,
  yet a receiver that first reported a wrong place is corrected once it settles).
- ``~/reset`` forgets the fix (the next plausible one locates); the parameters stay.
"""

from __future__ import annotations

from collections import Counter
import math

from rclpy.node import Node
from sensor_msgs.msg import NavSatFix, NavSatStatus

from mag_calibrator_ros.calibration.fit.earth_field import (
    EarthField,
    EarthFieldError,
    earth_field,
    location_problems,
)
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.nodes.answers import IoThread

Location = tuple[float, float, float]
"""(latitude deg north, longitude deg east, altitude m above the WGS84 ellipsoid)."""
LOCATION_PARAMETERS = ('latitude', 'longitude', 'altitude')
FIX_MOVE_M = 10_000.0
"""A plausible fix further than this from the fix in force replaces it. The model's field
changes slowly with place (the dip by about a degree per 100 km at mid-latitudes, the
intensity by a fraction of a percent), so this keeps the model well inside the smallest
``max_dip_error_deg`` while a fix stream leaves it alone."""
MAX_FIX_SD_M = FIX_MOVE_M
"""A fix whose reported horizontal standard deviation exceeds this is refused: the receiver
itself says it does not know where it is within the distance that matters."""
EARTH_RADIUS_M = 6_371_008.8
"""The mean Earth radius (IUGG), for the distance between two fixes."""
FIX_REFUSALS = ('no fix', 'no position', 'out of range', 'null island', 'uncertain')
"""Why a fix is refused, in the order they are checked (the keys of the counts)."""


def is_nan(value: object) -> bool:
    """A float NaN (the parameters' 'unknown'); anything else, even a bad type, is not."""
    return isinstance(value, float) and math.isnan(value)


def parameter_location_problems(latitude: object, longitude: object, altitude: object,
                                incomplete_ok: bool = False) -> list[str]:
    """What is wrong with these parameter values; NaN and NaN (no location) is fine, and so is
    one of the pair NaN with ``incomplete_ok`` (at run time: waiting for the other)."""
    if is_nan(latitude) and is_nan(longitude):
        return []
    if incomplete_ok and is_nan(latitude) != is_nan(longitude):  # the NaN one is not checked
        return location_problems(0.0 if is_nan(latitude) else latitude,
                                 0.0 if is_nan(longitude) else longitude, altitude)
    return location_problems(latitude, longitude, altitude)


def fix_refusal(fix: NavSatFix) -> str | None:
    """Why ``fix`` cannot locate the robot (one of FIX_REFUSALS), None when it is plausible."""
    if fix.status.status < NavSatStatus.STATUS_FIX:
        return 'no fix'
    if not (math.isfinite(fix.latitude) and math.isfinite(fix.longitude)):
        return 'no position'
    altitude_known = math.isfinite(fix.altitude)
    if location_problems(fix.latitude, fix.longitude, fix.altitude if altitude_known else 0.0):
        return 'out of range'
    if fix.latitude == 0.0 and fix.longitude == 0.0 and (not altitude_known
                                                         or fix.altitude == 0.0):
        return 'null island'
    if fix.position_covariance_type != NavSatFix.COVARIANCE_TYPE_UNKNOWN:
        east, north = fix.position_covariance[0], fix.position_covariance[4]  # m^2, ENU
        if not all(math.isfinite(v) and v <= MAX_FIX_SD_M ** 2 for v in (east, north)):
            return 'uncertain'
    return None


def fix_position(fix: NavSatFix) -> Location:
    """The location of a plausible fix (an unknown altitude counts as 0 m)."""
    altitude = fix.altitude if math.isfinite(fix.altitude) else 0.0
    return float(fix.latitude), float(fix.longitude), float(altitude)


def distance_m(a: Location, b: Location) -> float:
    """Great-circle distance between two locations (haversine on a sphere; altitude ignored)."""
    lat_a, lat_b = math.radians(a[0]), math.radians(b[0])
    d_lat, d_lon = lat_b - lat_a, math.radians(b[1] - a[1])
    h = math.sin(d_lat / 2) ** 2 + math.cos(lat_a) * math.cos(lat_b) * math.sin(d_lon / 2) ** 2
    return 2.0 * EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(h)))


class LocationSource:
    """Which location the World Magnetic Model should be evaluated at, and from where.

    ``wanted`` is (location, 'parameters' or 'gps/fix'), or None: no location. ``refused``
    counts refused fixes by reason; ``waiting`` says why a parameter pair is not in force.
    """

    def __init__(self, use_gps: bool = True) -> None:
        self.use_gps = use_gps
        self.refused: Counter[str] = Counter()
        self.waiting = ''
        self._parameters: Location | None = None
        self._fix: Location | None = None

    @property
    def wanted(self) -> tuple[Location, str] | None:
        if self._parameters is not None:
            return self._parameters, 'parameters'
        if self.use_gps and self._fix is not None:
            return self._fix, 'gps/fix'
        return None

    @property
    def fix(self) -> Location | None:
        """The fix that locates (or would, without the parameters), None until one is plausible."""
        return self._fix

    def set_parameters(self, latitude: float, longitude: float, altitude: float) -> None:
        """The parameters' values (validated): a location, none (both NaN), or half a pair,
        which waits for the other while the last complete pair stays in force."""
        lat_nan, lon_nan = math.isnan(latitude), math.isnan(longitude)
        if lat_nan != lon_nan:
            given, missing = ('longitude', 'latitude') if lat_nan else ('latitude', 'longitude')
            self.waiting = (f'{given} given, {missing} NaN: waiting for {missing} (set both, '
                            f'or both NaN for none); the location in force stays')
            return
        self.waiting = ''
        self._parameters = None if lat_nan else (latitude, longitude, altitude)

    def offer_fix(self, fix: NavSatFix) -> str | None:
        """Screen a fix (ignored without ``use_gps``); a plausible one locates when none did,
        or replaces the one in force when more than FIX_MOVE_M from it. Returns the refusal
        reason, None when plausible."""
        if not self.use_gps:
            return None
        reason = fix_refusal(fix)
        if reason is not None:
            self.refused[reason] += 1
            return reason
        where = fix_position(fix)
        if self._fix is None or distance_m(self._fix, where) > FIX_MOVE_M:
            self._fix = where
        return None

    def forget_fix(self) -> bool:
        """Forget the fix (``~/reset``); True when there was one."""
        had, self._fix = self._fix is not None, None
        return had

    def first_refusal(self, fix: NavSatFix) -> str | None:
        """The log line for a fix refused for a reason not seen before (None otherwise): each
        reason once, then only counted (gps_fixes_refused)."""
        reason = self.offer_fix(fix)
        if reason is None or self.refused[reason] != 1:
            return None
        return (f'gps/fix refused ({reason}: status {fix.status.status}, {fix.latitude}, '
                f'{fix.longitude}, altitude {fix.altitude}); counted in diagnostics '
                '(gps_fixes_refused), waiting for a plausible fix')

    def diagnostic_values(self, source: str) -> dict[str, object]:
        """/diagnostics values: where the location in force came from (``source``, '' none),
        what it waits for, the fixes refused by reason; only those that say something."""
        values: dict[str, object] = {}
        if source:
            values['location_source'] = source
        if self.waiting:
            values['location_waiting'] = self.waiting
        if self.refused_text():
            values['gps_fixes_refused'] = self.refused_text()
        return values

    def refused_text(self) -> str:
        """'null island: 3, no fix: 1' (empty when none was refused)."""
        return ', '.join(f'{reason}: {count}' for reason, count in self.refused.items())


class EarthFieldHere:
    """The World Magnetic Model's field where the robot is, kept in the session: evaluated on
    the I/O thread each time the location source wants another place, dropped when it wants
    none; every change is logged once."""

    def __init__(self, node: Node, session: CalibrationSession, io: IoThread) -> None:
        self._node, self._session, self._io = node, session, io
        self.source = LocationSource(bool(node.get_parameter('use_gps').value))
        self.asked: tuple[Location, str] | None = None  # the last place sent to the model
        self._in_force = ''  # 'parameters' or 'gps/fix' once the model's field is known

    def relocate(self) -> None:
        """Evaluate the model where the source now wants it (the parameters read afresh)."""
        source, node = self.source, self._node
        source.use_gps = bool(node.get_parameter('use_gps').value)
        source.set_parameters(*(float(node.get_parameter(name).value)
                                for name in LOCATION_PARAMETERS))
        wanted = source.wanted
        if wanted == self.asked:
            return
        self.asked = wanted
        if wanted is None:
            if self._in_force:
                node.get_logger().info('no location any more: fits are not checked against '
                                       'the World Magnetic Model until one is given')
            self._in_force = ''
            self._session.set_earth_field(None)
            return
        where, source_name = wanted
        self._io.run(lambda: earth_field(*where)).add_done_callback(
            lambda future: self._located(where, source_name, future.result()))

    def on_fix(self, msg: NavSatFix) -> None:
        """Screen the fix; a plausible one locates, or replaces a far one (LocationSource)."""
        refused = self.source.first_refusal(msg)
        if refused is not None:
            self._node.get_logger().warning(refused)
        if self.source.wanted != self.asked:
            self.relocate()

    def forget_fix(self) -> bool:
        """``~/reset``: forget the fix's location (the next plausible fix locates)."""
        forgot = self.source.forget_fix()
        self.relocate()
        return forgot

    def diagnostic_values(self) -> dict[str, object]:
        return self.source.diagnostic_values(self._in_force)

    def _located(self, where: Location, source: str, result: EarthField | Exception) -> None:
        if (where, source) != self.asked:
            return  # another location was asked for meanwhile
        logger = self._node.get_logger()
        if isinstance(result, Exception):
            what = '' if isinstance(result, EarthFieldError) else f'{type(result).__name__}: '
            logger.warning(f'no World Magnetic Model field at {where} (from {source}): '
                           f'{what}{result}; running without it')
            self._in_force = ''
            self._session.set_earth_field(None)  # not a field from elsewhere
            return
        self._in_force = source
        self._session.set_earth_field(result)
        logger.info(f'earth field here (from {source}): {result.describe()}')
        for note in result.notes:
            logger.warning(note)
