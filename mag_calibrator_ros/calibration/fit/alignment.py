# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Magnetometer-to-IMU alignment from gravity: the rotation that makes the dip angle constant.

A hard- and soft-iron fit makes the field a sphere but cannot see how that sphere is rotated
against the robot's IMU: any rotation of a sphere is a sphere. Gravity can. Held still, an
accelerometer measures the specific force ``a`` (up), and in a uniform field the angle between
``a`` and the field is the same in every attitude: ``asin(a . R u) = -dip`` for unit vectors and
the right rotation ``R`` from the corrected magnetometer frame to the accelerometer frame. Finding
the ``R`` (and dip) that makes that angle constant over attitudes spread across distinct gravity
directions is the alignment of MAG.I.C.AL. (Papafotis & Sotiriadis, IEEE Sensors J. 19(23), 2019)
and of Kok & Schön ("Magnetometer calibration using inertial sensors", IEEE Sensors J. 16(14),
2016); Vasconcelos et al. (IEEE Trans. Instrum. Meas. 60(2), 2011) solve the same alignment with
an orthogonal Procrustes step. Here:

1. ``StaticAttitudes`` keeps, O(1) per reading, quasi-static stretches of a paired
   (magnetometer, accelerometer[, gyroscope]) stream, each averaged into one *attitude*, and a
   bounded set of distinct ones;
2. ``estimate_alignment`` screens them (``|a|`` near its median: not accelerating; ``|M (m -
   b)|`` near F: no spike), starts from the linear solution of ``a_i^T X u_i = s`` (any
   rotation, 90/180 deg flips included, with no local minimum to fall into), projects it onto
   the rotations (Procrustes, via SVD) and refines rotation and dip by robust least squares on
   the dip angles, then by plain least squares on the inliers (the rotation that minimises the
   dip's scatter).

A rotation cannot undo a left-handed axis remap (a swapped or single inverted axis): angles are
kept by reflections too, so the best rotation then fits the *negated* dip. Knowing the sign of
the inclination (from the World Magnetic Model at the robot's location) tells the two apart. A
large rotation (a 90 or 180 deg flip, as the AK09916's y/z inversion gives) is a mounting or
driver error rather than a few degrees of misalignment: it is named with the axis remap that
fixes it and not applied (ArduPilot's COMPASS_AUTO_ROT finds such rotations likewise).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import itertools
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.ellipsoid import robust_sigma

# -- collecting quasi-static attitudes ------------------------------------------------------------

STILL_ANGLE_DEG = 2.0
"""Readings of one still stretch: the accelerometer's direction within this of the first."""
STILL_MAGNITUDE = 0.02
"""... and its magnitude within 2 % of the first (a push shows here first)."""
STILL_FIELD_ANGLE_DEG = 4.0
"""Without a gyroscope: the raw field within this angle (of the field's radius) of the first, so
a turn about the vertical, which the accelerometer cannot see, ends the stretch."""
MAX_STILL_RATE = 0.1
"""rad/s: faster than this (6 deg/s) is not still; a hand holding a board still stays below."""
MIN_STILL_S = 0.2
"""With a gyroscope, a stretch shorter than this is passing through, not held."""
MAX_GAP_S = 1.0
"""A gap longer than this between paired readings ends a stretch."""
ATTITUDE_CAPACITY = 300
"""Attitudes kept (a slow log without a gyroscope gives one per reading); more cost fit time."""
MERGE_DISTANCE = math.radians(2.0)
"""A new attitude this close to a kept one (gravity and field directions) is the same pose held
again: the two are averaged, weighted by their readings."""
ATTITUDE_WIDTH = 8
"""Attitude rows: mean raw field (3), mean specific force (3), readings, seconds held (without a
clock: the readings of its longest single stretch)."""
HELD_FACTOR = 4.0
"""Without a clock: a stretch of this many times the median stretch's readings (and at least
MIN_HELD_READINGS) was held, where a stretch in motion ends after a few. A fast log's holds
stand out so; a slow log's readings are each a stretch of one, and every one is used."""
MIN_HELD_READINGS = 3

# -- estimating the rotation ----------------------------------------------------------------------

MIN_ATTITUDES = 6
MIN_SPREAD_DEG = 10.0
"""The gravity directions must spread at least this far: about a single gravity direction the
rotation is unobservable (a ground robot that never tilts determines only two of its three
angles)."""
MAX_ACCEL_ERROR = 0.03
"""An attitude is static when |a| is within 3 % of the median |a| (about 0.3 m/s^2)."""
MAX_FIELD_ERROR = 0.05
"""... and its corrected |field| within 5 % of F (a spike or a magnet is not the earth's)."""
MAX_ROTATION_STD_DEG = 1.0
"""Largest 1-sigma uncertainty of the rotation (about its worst axis) still applied."""
MAX_DIP_STD_DEG = 5.0
"""A dip scattering more than this after the best rotation is not determined: the readings were
not static or the field is not uniform."""
MAX_ANGLE_DEG = 15.0
"""A larger rotation is a mounting or axis-remap error to fix at the source, not applied."""
OUTLIER_SIGMAS = 3.5
ROBUST_PASSES = 4
MIN_SCALE_DEG = 0.02
"""Floor of the robust scale of the dip residuals (noise-free synthetic data)."""
HANDEDNESS_MIN_DIP_DEG = 10.0
"""Near the magnetic equator the dip's sign cannot tell a reflection from a rotation."""


class StaticAttitudes:
    """Quasi-static attitudes from a paired (magnetometer, accelerometer, gyroscope) stream.

    ``add`` costs O(1) per reading (O(capacity) when a stretch ends), so it runs on the message
    path; ``snapshot`` gives the attitudes for a fit job. A stretch is still while the gyroscope
    (when given) stays below MAX_STILL_RATE and the accelerometer (and, once ``field_scale`` is
    known, the raw field) stays within a few degrees of its first reading; it becomes one
    attitude, the average of its readings, if it lasted MIN_STILL_S. A lone reading counts only
    when its neighbours are MIN_STILL_S away or more (a slow log): at a high rate, a reading that
    starts no still stretch is the board passing through, accelerating. ``field_scale`` (the
    field's radius in raw units, set by the owner once known) lets the field tell a turn about
    the vertical, which the accelerometer cannot see, and tells poses apart.

    ``clock=False`` is for a log without time stamps, whose rate nobody knows: stillness is
    then judged without time (no MIN_STILL_S, no MAX_GAP_S), by consecutive readings whose
    accelerometer (and field) directions agree as above, and the log's own rows tell held
    from passing: in a fast log (consecutive readings agree even in motion, so the median
    stretch has two readings or more), or when at least MIN_ATTITUDES stretches last
    HELD_FACTOR times the median, only those long stretches are attitudes; in a slow log
    (each reading its own stretch) every stretch is. ``estimate_alignment`` screens them (|a|
    near g, a clean field, robust to a few taken in motion), so no guessed rate can make or
    break it; a slow log moved fast cannot be told from one moved slowly, and those screens
    are then its only guard.
    """

    def __init__(self, capacity: int = ATTITUDE_CAPACITY, clock: bool = True) -> None:
        self.capacity = int(capacity)
        self.clock = bool(clock)
        self._rows = np.zeros((self.capacity, ATTITUDE_WIDTH))
        self.fill = 0
        self.stretches = 0
        """Still stretches that became attitudes (kept, merged or replacing one)."""
        self.readings = 0
        """Paired readings offered."""
        self.refused = 0
        """Readings with a non-finite or zero value."""
        self.field_scale: float | None = None
        self._lengths: dict[int, int] = {}
        """Without a clock: how many stretches had each number of readings (capped)."""
        self._last_time = -math.inf
        # [sums (6), count, start, end, first accel (ax, ay, az, |a|), first field, gyro, gap]
        self._open: list | None = None
        self._cos_still = math.cos(math.radians(STILL_ANGLE_DEG))
        self._field_tolerance = math.tan(math.radians(STILL_FIELD_ANGLE_DEG))

    def clear(self) -> None:
        self.fill = 0
        self._lengths = {}
        self._open = None
        self._last_time = -math.inf

    def add(self, time_s: float, field: np.ndarray, accel: np.ndarray,
            gyro: np.ndarray | None = None) -> None:
        """One paired reading (raw field, specific force, angular rate in rad/s or None)."""
        self.readings += 1
        mx, my, mz = (float(v) for v in field)
        ax, ay, az = (float(v) for v in accel)
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        gap, self._last_time = time_s - self._last_time, time_s
        if not (math.isfinite(mx + my + mz) and math.isfinite(norm) and norm > 0.0):
            self.refused += 1
            self._close(time_s)
            return
        has_gyro = gyro is not None
        still = True
        if has_gyro:
            gx, gy, gz = (float(v) for v in gyro)
            still = math.sqrt(gx * gx + gy * gy + gz * gz) <= MAX_STILL_RATE  # NaN: not still
        reading = (mx, my, mz)
        segment = self._open
        if segment is not None:
            if still and self._continues(segment, time_s, reading, (ax, ay, az), norm, has_gyro):
                sums = segment[0]
                sums[0] += mx
                sums[1] += my
                sums[2] += mz
                sums[3] += ax
                sums[4] += ay
                sums[5] += az
                segment[1] += 1
                segment[3] = time_s
                return
            self._close(time_s)
        if still:
            self._open = [[mx, my, mz, ax, ay, az], 1, time_s, time_s, (ax, ay, az, norm),
                          reading, has_gyro, gap]

    def _continues(self, segment: list, time_s: float, reading: tuple, accel: tuple,
                   norm: float, has_gyro: bool) -> bool:
        first_a = segment[4]
        if has_gyro != segment[6] or self.clock and not 0.0 <= time_s - segment[3] <= MAX_GAP_S:
            return False
        if abs(norm / first_a[3] - 1.0) > STILL_MAGNITUDE:
            return False
        cosine = (accel[0] * first_a[0] + accel[1] * first_a[1] + accel[2] * first_a[2]) / (
            norm * first_a[3])
        if cosine < self._cos_still:
            return False
        scale = self.field_scale
        if scale is not None and scale > 0.0:
            if math.dist(reading, segment[5]) > self._field_tolerance * scale:
                return False
        return True

    def _close(self, next_time: float) -> None:
        segment, self._open = self._open, None
        if segment is None:
            return
        sums, count, start, end, _, _, _, gap = segment
        held = end - start >= MIN_STILL_S
        alone = count == 1 and gap >= MIN_STILL_S and next_time - end >= MIN_STILL_S
        if self.clock and not (held or alone):
            return
        if not self.clock and not segment[6]:
            length = min(count, 1 << 16)
            self._lengths[length] = self._lengths.get(length, 0) + 1
        row = np.array([*(value / count for value in sums), count,
                        end - start if self.clock else count])
        self._keep(row)

    def _keep(self, row: np.ndarray) -> None:
        self.stretches += 1
        if self.fill == 0:
            self._rows[0] = row
            self.fill = 1
            return
        kept = self._rows[: self.fill]
        distance = _attitude_distance(kept, row, self.field_scale)
        nearest = int(np.argmin(distance))
        if self.field_scale and distance[nearest] <= MERGE_DISTANCE:
            old = kept[nearest]
            total = old[6] + row[6]
            old[:6] = (old[:6] * old[6] + row[:6] * row[6]) / total
            old[6] = total
            old[7] = old[7] + row[7] if self.clock else max(old[7], row[7])
        elif self.fill < self.capacity:
            self._rows[self.fill] = row
            self.fill += 1
        elif self.clock or row[7] >= kept[nearest, 7]:
            self._rows[nearest] = row  # keeps the set spread: a new pose displaces its nearest

    def finish(self) -> None:
        """End the open stretch (the end of a recording)."""
        self._close(math.inf)

    def snapshot(self) -> np.ndarray:
        """The attitudes so far (n, ATTITUDE_WIDTH), a copy, with the stretch still open when it
        has lasted MIN_STILL_S (the sensor held still while a calibration is asked for)."""
        rows = self._rows[: self.fill].copy()
        segment = self._open
        if segment is not None and (not self.clock or segment[3] - segment[2] >= MIN_STILL_S):
            count = segment[1]
            current = [*(value / count for value in segment[0]), count,
                       segment[3] - segment[2] if self.clock else count]
            rows = np.vstack([rows, current])
        if not self.clock and self._lengths:
            median = self.median_stretch()
            held = rows[:, 7] >= max(MIN_HELD_READINGS, HELD_FACTOR * median)
            if median >= 2 or np.count_nonzero(held) >= MIN_ATTITUDES:
                rows = rows[held]
        return rows

    def median_stretch(self) -> int:
        """Without a clock: the median readings of the stretches judged without a gyroscope
        (a gyroscope judges stillness by itself, clock or none); 0 when there are none."""
        total = sum(self._lengths.values())
        seen = 0
        for length in sorted(self._lengths):
            seen += self._lengths[length]
            if 2 * seen >= total:
                return length
        return 0


def _attitude_distance(kept: np.ndarray, row: np.ndarray, scale: float | None) -> np.ndarray:
    """Gravity direction difference, plus the field's difference relative to its radius when
    that is known (two headings at one tilt are two attitudes)."""
    accel = kept[:, 3:6] / np.linalg.norm(kept[:, 3:6], axis=1)[:, None]
    distance = np.linalg.norm(accel - row[3:6] / np.linalg.norm(row[3:6]), axis=1)
    if scale:
        distance += np.linalg.norm(kept[:, :3] - row[:3], axis=1) / scale
    return distance


# -- the estimate ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class AlignmentOptions:
    """Gates of the alignment; ``expected_inclination_deg`` (the World Magnetic Model's, when
    the location is known) tells a left-handed remap from the southern hemisphere."""

    min_attitudes: int = MIN_ATTITUDES
    min_spread_deg: float = MIN_SPREAD_DEG
    max_accel_error: float = MAX_ACCEL_ERROR
    max_field_error: float = MAX_FIELD_ERROR
    max_rotation_std_deg: float = MAX_ROTATION_STD_DEG
    max_dip_std_deg: float = MAX_DIP_STD_DEG
    max_angle_deg: float = MAX_ANGLE_DEG
    expected_inclination_deg: float | None = None


@dataclass(frozen=True)
class Alignment:
    """The rotation from the corrected magnetometer frame to the accelerometer frame, and the dip.

    ``success``: determined and applicable (``reason`` says why not: too few static attitudes,
    gravity directions too close, not determined, or a gross mounting error, named in ``remap``).
    ``rotation`` is the best proper rotation found even when it is not applied. ``dip_deg`` is
    positive when the field points below the horizon; ``dip_std_deg`` its scatter over the
    ``static_samples`` inlying attitudes with ``rotation``, ``dip_std_before_deg`` with none.
    """

    success: bool
    reason: str
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    angle_deg: float = math.nan
    dip_deg: float = math.nan
    dip_std_deg: float = math.nan
    dip_std_before_deg: float = math.nan
    static_samples: int = 0
    attitudes: int = 0
    outliers: int = 0
    rotation_std_deg: float = math.nan
    handedness: str = 'unknown'
    """'right', 'left' (a reflection: no rotation fixes it) or 'unknown' (no expected dip)."""
    remap: str = ''
    """For a gross error: the axis remap that fixes it, e.g. '(x, -y, -z)'."""
    note: str = ''

    def as_dict(self) -> dict:
        """The ``alignment`` object of ``mag_calibrator_fit --json``."""
        def number(value: float) -> float | None:
            return float(value) if math.isfinite(value) else None

        return {
            'rotation': [float(v) for v in np.asarray(self.rotation).reshape(9)],
            'angle_deg': number(self.angle_deg),
            'dip_deg': number(self.dip_deg),
            'dip_std_deg': number(self.dip_std_deg),
            'static_samples': int(self.static_samples),
            'applied': bool(self.success),
            'reason': self.reason,
            'dip_std_before_deg': number(self.dip_std_before_deg),
            'rotation_std_deg': number(self.rotation_std_deg),
            'handedness': self.handedness,
            'remap': self.remap,
        }

    def metadata(self) -> dict[str, float | int]:
        """What a calibration records about the alignment it carries."""
        return {'alignment_angle_deg': round(float(self.angle_deg), 4),
                'dip_deg': round(float(self.dip_deg), 4),
                'dip_std_deg': round(float(self.dip_std_deg), 4),
                'static_samples': int(self.static_samples)}

    def summary(self) -> str:
        """One line for a log or a service answer."""
        if not math.isfinite(self.dip_deg):
            return f'alignment not determined: {self.reason}'
        text = (f'rotation {self.angle_deg:.2f} deg, dip {self.dip_deg:.2f} deg \u00b1 '
                f'{self.dip_std_deg:.2f} deg over {self.static_samples} static attitudes '
                f'(\u00b1 {self.dip_std_before_deg:.2f} deg unaligned)')
        if self.success:
            return f'aligned to the IMU: {text}'
        return f'alignment not applied ({self.reason}); {text}'


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """The angle of a rotation matrix, degrees (0..180)."""
    cosine = (float(np.trace(rotation)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cosine))))


def _units(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.linalg.norm(vectors, axis=1)[:, None]


def _dips(accel: np.ndarray, field: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """asin(a . R u) per attitude, radians: minus the dip."""
    return np.arcsin(np.clip(np.sum(accel * (field @ rotation.T), axis=1), -1.0, 1.0))


def _linear_rotation(accel: np.ndarray, field: np.ndarray) -> tuple[np.ndarray, float]:
    """The rotation from the null vector of [vec(a u^T), -1] (X ~ R, s ~ a . R u), projected
    onto proper rotations; and the ratio of the two smallest singular values (how well the null
    vector is determined: near 1, it is not)."""
    design = np.hstack([np.einsum('ni,nj->nij', accel, field).reshape(-1, 9),
                        -np.ones((len(accel), 1))])
    _, singular, vt = np.linalg.svd(design, full_matrices=False)
    matrix = vt[-1, :9].reshape(3, 3)
    if np.linalg.det(matrix) < 0.0:
        matrix = -matrix  # (X, s) and (-X, -s) fit alike; the proper one is the rotation
    u, _, wt = np.linalg.svd(matrix)
    rotation = u @ wt
    if np.linalg.det(rotation) < 0.0:  # a degenerate X: flip the weakest direction
        u[:, -1] = -u[:, -1]
        rotation = u @ wt
    ratio = singular[-1] / singular[-2] if singular[-2] > 0.0 else 1.0
    return rotation, float(ratio)


def _refine(accel: np.ndarray, field: np.ndarray, start: np.ndarray, scale: float | None
            ) -> tuple[np.ndarray, float, float, np.ndarray]:
    """Rotation and mean dip residual: robust (soft-L1 at ``scale``) or plain (None)."""
    from scipy.optimize import least_squares  # the fit worker's import, never a node's start-up
    from scipy.spatial.transform import Rotation
    def residuals(x: np.ndarray) -> np.ndarray:
        rotation = Rotation.from_rotvec(x[:3]).as_matrix() @ start
        return _dips(accel, field, rotation) - x[3]

    x0 = np.array([0.0, 0.0, 0.0, float(np.mean(_dips(accel, field, start)))])
    if scale is None:
        solution = least_squares(residuals, x0, method='lm', x_scale=1.0)
    else:
        solution = least_squares(residuals, x0, loss='soft_l1', f_scale=scale)
    rotation = Rotation.from_rotvec(solution.x[:3]).as_matrix() @ start
    return rotation, float(solution.x[3]), float(solution.cost), solution.jac


def _spread_deg(accel: np.ndarray) -> float:
    """How far the gravity directions spread: asin of the root of the scatter matrix's second
    eigenvalue (two directions 2x apart give x)."""
    eigenvalues = np.linalg.eigvalsh(accel.T @ accel / len(accel))
    return math.degrees(math.asin(min(1.0, math.sqrt(max(float(eigenvalues[1]), 0.0)))))


def estimate_alignment(attitudes: np.ndarray, calibration: Calibration,
                       options: AlignmentOptions = AlignmentOptions()) -> Alignment:
    """The alignment of ``calibration``'s corrected field (``M (m - b)``, before any rotation it
    carries) to the accelerometer, from ``StaticAttitudes.snapshot()`` rows. Never raises on
    data; a failed gate gives ``success`` False with the reason."""
    rows = np.asarray(attitudes, dtype=float).reshape(-1, ATTITUDE_WIDTH)
    offered = len(rows)
    with np.errstate(all='ignore'):
        field = calibration.unrotated(rows[:, :3])
        accel = rows[:, 3:6]
        field_norm = np.linalg.norm(field, axis=1)
        accel_norm = np.linalg.norm(accel, axis=1)
    usable = np.isfinite(field_norm) & np.isfinite(accel_norm) & (field_norm > 0) & (
        accel_norm > 0)
    static = usable.copy()
    if usable.any():
        gravity = float(np.median(accel_norm[usable]))
        static &= np.abs(accel_norm / gravity - 1.0) <= options.max_accel_error
        static &= np.abs(field_norm / calibration.field_strength - 1.0) <= options.max_field_error
    count = int(static.sum())
    if count < options.min_attitudes:
        return Alignment(False, f'too few static attitudes ({count} of {offered} held still '
                         f'with |a| near g and a clean field; {options.min_attitudes} needed): '
                         'hold the sensor still for a second at several different tilts',
                         attitudes=offered, static_samples=count)
    accel_units = _units(accel[static])
    field_units = _units(field[static])
    spread = _spread_deg(accel_units)
    before = float(np.degrees(np.std(_dips(accel_units, field_units, np.eye(3)))))
    if spread < options.min_spread_deg:
        return Alignment(False, f'gravity directions too close (the static attitudes spread '
                         f'{spread:.1f} deg, {options.min_spread_deg:g} deg needed): tilt the '
                         'sensor (roll it, stand it on its sides) and hold it still each time',
                         attitudes=offered, static_samples=count, dip_std_before_deg=before)
    start, _ = _linear_rotation(accel_units, field_units)
    floor = math.radians(MIN_SCALE_DEG)
    start_dips = _dips(accel_units, field_units, start)
    scale = max(robust_sigma(start_dips, about_median=True, floor=None), floor)
    candidates = [_refine(accel_units, field_units, guess, scale)
                  for guess in (start, np.eye(3))]
    rotation, offset, _, _ = min(candidates, key=lambda candidate: candidate[2])
    for _ in range(ROBUST_PASSES):  # the linear start's scale counts the outliers: tighten it
        residuals = _dips(accel_units, field_units, rotation) - offset
        tighter = max(robust_sigma(residuals, about_median=True, floor=None), floor)
        if tighter > 0.8 * scale:
            break
        scale = tighter
        rotation, offset, _, _ = _refine(accel_units, field_units, rotation, scale)
    residuals = _dips(accel_units, field_units, rotation) - offset
    sigma = max(robust_sigma(residuals, about_median=True, floor=None), floor)
    inliers = np.abs(residuals) <= OUTLIER_SIGMAS * sigma
    if inliers.sum() < options.min_attitudes:
        inliers = np.ones(count, dtype=bool)
    rotation, offset, cost, jacobian = _refine(accel_units[inliers], field_units[inliers],
                                               rotation, None)
    used = int(inliers.sum())
    dips = _dips(accel_units[inliers], field_units[inliers], rotation)
    dip = -math.degrees(float(np.mean(dips)))
    dip_std = math.degrees(float(np.std(dips)))
    rotation_std = _rotation_std_deg(jacobian, 2.0 * cost, used)
    angle = rotation_angle_deg(rotation)
    common = dict(rotation=rotation, angle_deg=angle, dip_deg=dip, dip_std_deg=dip_std,
                  dip_std_before_deg=before, static_samples=used, attitudes=offered,
                  outliers=count - used, rotation_std_deg=rotation_std)
    handedness, note = _handedness(dip, options.expected_inclination_deg, rotation)
    if handedness == 'left':
        remap, residual = nearest_remap(-rotation)
        return Alignment(False, f'a wrong location or left-handed axes: the dip comes out '
                         f'{dip:.1f} deg where the model says '
                         f'{options.expected_inclination_deg:.1f} deg at the location given. '
                         'Either the location is wrong (the other hemisphere? check latitude '
                         'and longitude, or the gps/fix), or the magnetometer axes are a '
                         "reflection of the accelerometer's, which no rotation can fix: then "
                         f'remap the magnetometer (x, y, z) -> {remap} in its driver'
                         + (f' (then {residual:.1f} deg remain)' if residual >= 1.0 else ''),
                         handedness=handedness, remap=remap, note=note, **common)
    if angle > options.max_angle_deg:
        remap, residual = nearest_remap(rotation)
        described = describe_rotation(rotation)
        return Alignment(False, f'gross mounting error: the magnetometer axes are rotated '
                         f"{described} against the accelerometer's; remap the magnetometer "
                         f'(x, y, z) -> {remap} in its driver'
                         + (f' (then {residual:.1f} deg remain)' if residual >= 1.0 else '')
                         + f' (rotations above max_alignment_deg {options.max_angle_deg:g} deg '
                         'are not applied)', handedness=handedness, remap=remap, note=note,
                         **common)
    if not rotation_std <= options.max_rotation_std_deg:
        return Alignment(False, f'rotation not determined (uncertainty {rotation_std:.2f} deg, '
                         f'{options.max_rotation_std_deg:g} deg allowed): hold still at more, '
                         'more different tilts', handedness=handedness, note=note, **common)
    if dip_std > options.max_dip_std_deg:
        return Alignment(False, f'dip not determined: it scatters by {dip_std:.1f} deg even '
                         'after the best rotation (readings not static, or the field not '
                         'uniform here)', handedness=handedness, note=note, **common)
    return Alignment(True, 'ok', handedness=handedness, note=note, **common)


def _rotation_std_deg(jacobian: np.ndarray, sum_squares: float, count: int) -> float:
    """1-sigma uncertainty of the rotation about its worst-determined axis (Gauss-Newton)."""
    if count <= 4:
        return math.inf
    variance = sum_squares / (count - 4)
    try:
        covariance = np.linalg.inv(jacobian.T @ jacobian) * variance
    except np.linalg.LinAlgError:
        return math.inf
    worst = float(np.max(np.linalg.eigvalsh(covariance[:3, :3])))
    return math.degrees(math.sqrt(worst)) if worst >= 0.0 and math.isfinite(worst) else math.inf


def _handedness(dip_deg: float, expected_deg: float | None, rotation: np.ndarray
                ) -> tuple[str, str]:
    if expected_deg is None or not math.isfinite(expected_deg):
        if dip_deg < -HANDEDNESS_MIN_DIP_DEG:
            remap, _ = nearest_remap(-rotation)
            return 'unknown', (f'the field points up ({dip_deg:.1f} deg): the southern '
                               'hemisphere, or left-handed magnetometer axes (remap (x, y, z) '
                               f'-> {remap}); give the location to tell')
        return 'unknown', ''
    if abs(expected_deg) < HANDEDNESS_MIN_DIP_DEG or abs(dip_deg) < HANDEDNESS_MIN_DIP_DEG:
        return 'unknown', 'near the magnetic equator the dip cannot tell left- from right-handed'
    return ('left' if (dip_deg > 0.0) != (expected_deg > 0.0) else 'right'), ''


def _signed_permutations() -> list[np.ndarray]:
    matrices = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            for row, (column, sign) in enumerate(zip(order, signs, strict=True)):
                matrix[row, column] = sign
            matrices.append(matrix)
    return matrices


SIGNED_PERMUTATIONS = tuple(_signed_permutations())
"""The 48 axis remaps (24 rotations, 24 reflections)."""


def nearest_remap(matrix: np.ndarray) -> tuple[str, float]:
    """The axis remap nearest an orthogonal ``matrix`` (same handedness), as text ('(x, -y, -z)':
    new x = x, new y = -y ...), and the angle in degrees left between them."""
    determinant = np.sign(np.linalg.det(matrix))
    best = min((p for p in SIGNED_PERMUTATIONS if np.sign(np.linalg.det(p)) == determinant),
               key=lambda p: float(np.linalg.norm(matrix - p)))
    return remap_text(best), rotation_angle_deg(matrix @ best.T)


def remap_text(remap: np.ndarray) -> str:
    names = 'xyz'
    parts = []
    for row in np.asarray(remap):
        column = int(np.argmax(np.abs(row)))
        parts.append(('-' if row[column] < 0 else '') + names[column])
    return '(' + ', '.join(parts) + ')'


def describe_rotation(rotation: np.ndarray) -> str:
    """'180 deg about x', '90 deg about z', '120 deg about (0.58, 0.58, 0.58)'."""
    from scipy.spatial.transform import Rotation
    vector = Rotation.from_matrix(rotation).as_rotvec()
    angle = math.degrees(float(np.linalg.norm(vector)))
    if angle < 1e-9:
        return '0 deg'
    axis = vector / np.linalg.norm(vector)
    main = int(np.argmax(np.abs(axis)))
    if angle > 179.9 and axis[main] < 0.0:
        axis = -axis  # 180 deg about -x is 180 deg about x
    if abs(axis[main]) > math.cos(math.radians(5.0)):
        sign = '-' if axis[main] < 0 else ''
        return f'{angle:.0f} deg about {sign}{"xyz"[main]}'
    return f'{angle:.0f} deg about ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f})'


__all__ = [
    'ATTITUDE_CAPACITY',
    'ATTITUDE_WIDTH',
    'MAX_ANGLE_DEG',
    'SIGNED_PERMUTATIONS',
    'Alignment',
    'AlignmentOptions',
    'StaticAttitudes',
    'describe_rotation',
    'estimate_alignment',
    'nearest_remap',
    'remap_text',
    'rotation_angle_deg',
]
