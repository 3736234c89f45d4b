# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Gravity's direction in the IMU frame, and which accelerometer samples measured it.

An accelerometer measures gravity and the robot's own acceleration together: a ground robot
starting to drive at 0.5 m/s^2 reads as a tilt of 2.9°, and a planar fit levelled by those
readings takes it for one (``fit/levelled.py``): the vertical field no longer fits, so the fit
makes it vanish and reports a dip near zero and an offset along the turning axis far from the
truth. Only the gyroscope tells a rotation from an acceleration.

``GravityTracker`` is a complementary filter (Mahony, Hamel and Pflimlin, "Nonlinear
Complementary Filters on the Special Orthogonal Group", IEEE TAC 53(5), 2008) for gravity's
direction alone: the gyroscope carries it from sample to sample, and it is pulled towards the
accelerometer's (low-passed against vibration) while the two agree, which also learns the
gyroscope's bias about the tilt axes. A specific force further than GRAVITY_DEG from where the
gyroscope carried gravity is the robot accelerating: it corrects nothing and measures no
gravity, as x-io Fusion rejects accelerations (github.com/xioTechnologies/Fusion,
``FusionAhrs.c``, acceleration rejection and recovery). Only directions are used, so any unit
of the accelerometer serves; the gyroscope is in rad/s.

A gyroscope that does not turn with the accelerometer (in deg/s where sensor_msgs/Imu asks
rad/s, or about other axes) makes every tilt look like an acceleration, and nothing else would
say so: ``RateCheck`` compares the two turnings and names the likely cause. It only says; what
the tracker gives is the same either way (a multirotor in flight disagrees too, its
accelerometer reading thrust, and there taking the accelerometer for gravity would be wrong).

What it cannot tell: an acceleration that builds up slowly (0.5 m/s^2 reached over a second)
is followed as it grows, at CORRECTION_S, and passes as a tilt as it would without a
gyroscope; so does one that lasts longer than RESTART_S.
"""

from __future__ import annotations

import math

Vector = tuple[float, float, float]

LOWPASS_S = 0.1
"""Time constant of the accelerometer's low-pass (carried by the gyroscope, so a turn does not
smear it): a floor's and motors' vibration above a few hertz averages out, while a drive's
acceleration (a few tenths of a second or more) stays and is rejected."""
CORRECTION_S = 0.25
"""Time constant with which the tracked direction follows the accelerometer's while they agree.
An unlearnt gyroscope bias about a tilt axis makes it lag by bias x CORRECTION_S (0.25° for
1 °/s) until BIAS_S has learnt it."""
BIAS_S = 10.0
"""Time constant with which the gyroscope's bias about the tilt axes is learnt (the integral
term; the bias about gravity moves nothing this tracks)."""
MAX_BIAS_RAD_S = math.radians(20.0)
"""The largest bias learnt: four times the ICM-20948's initial zero-rate tolerance (±5 °/s,
DS-000189 table 1); more is no bias."""
GRAVITY_DEG = 1.0
"""A specific force within this of the tracked direction is gravity: an acceleration that
starts within a few tenths of a second is caught from 0.17 m/s^2 (a tenth of what a robot
starting to drive gives); the accelerometer's noise after the low-pass is a few hundredths of a
degree."""
SETTLE_S = 1.0
"""After a (re)start nothing counts as gravity for this long: four correction time constants."""
RESTART_S = 3.0
"""Samples rejected for this long in a row restart the tracker on the accelerometer (its
direction had drifted, or the robot was turned while nothing tracked). A constant acceleration
that lasts longer (an arc driven for seconds) is then taken for a tilt."""
MAX_STEP_S = 0.25
"""A gap between samples longer than this (or a stamp going back, another frame) restarts the
tracker: the gyroscope no longer carries the direction across it."""


RATE_WINDOW_S = 0.05
"""The accelerometer's direction and the gyroscope's turning of it are compared over windows this
long: short, so that even in deg/s the gyroscope turns it well under half a turn in one."""
RATE_MIN_TURN = 0.0125
"""A window counts when the gyroscope turns gravity's direction at least this far in it (rad:
0.25 rad/s of tilting): beyond what a gyroscope bias not learnt yet predicts (the ICM-20948's
zero-rate tolerance is ±5 °/s an axis, DS-000189 table 1; 7 °/s about a tilt axis is 0.006 rad
a window), and well above the accelerometer's noise between two samples. A ground robot turning
about gravity predicts none and is never judged."""
RATE_WINDOWS = 100
"""Windows counted before the comparison judges (five seconds of tilting), and over which it
keeps judging (an exponential mean): one shock or glitch moves it by a few hundredths at most;
a gyroscope that changes (a driver restarted in another unit) is followed within seconds."""
RATE_DISAGREE = 0.3
"""The two disagree when the accelerometer turns less than this share of what the gyroscope
predicts (deg/s read as rad/s: 1/57; other axes: about 0 or less; a multirotor in flight: 0 to
0.2), and agree again from RATE_AGREE (a handheld IMU: 0.9 and more). Noise pulls the share
towards 1 (a window's start is noisy too, and the gyroscope turns its noise with it): an
accelerometer that shakes by more than the tilts move it can hide a deg/s gyroscope, never
invent one."""
RATE_AGREE = 0.5
RATE_CLIP = (-1.0, 3.0)
"""One window's share is clipped to this, symmetric about agreement: a window the robot's
acceleration dominates cannot outvote many."""
DEGREES_BETTER = 4.0
"""deg/s is named when the rates read as deg/s predict the accelerometer's turning this many
times better (in the mean squared miss) than as they came."""
RAD_PER_DEG = math.pi / 180.0


class RateCheck:
    """How far the accelerometer's direction turns per turn the gyroscope predicts for it: the
    mean over windows of RATE_WINDOW_S of each window's share (the measured change projected on
    the predicted one), from the raw directions (no low-pass lags the one behind the other); 1
    when both agree. Beside it, how much better the rates would predict read as deg/s: the one
    mistake common enough to name."""

    def __init__(self) -> None:
        self.agree = True
        self._start: Vector | None = None  # the measured direction at the window's start
        self._turned: Vector = (0.0, 0.0, 1.0)  # it, turned by the gyroscope since
        self._turned_deg: Vector = (0.0, 0.0, 1.0)  # it, turned by the rates read as deg/s
        self._elapsed_s = 0.0
        self._counted = 0
        self._mean = 0.0
        self._misfit = 0.0  # mean |measured change - predicted|^2 over the windows counted
        self._misfit_deg = 0.0  # the same with the rates read as deg/s

    def update(self, measured: Vector, rate: Vector | None, step_s: float) -> None:
        """One sample; ``rate`` None (a gap, a restart) starts a new window."""
        if rate is None or self._start is None:
            self._start = self._turned = self._turned_deg = measured
            self._elapsed_s = 0.0
            return
        self._turned = _carried(self._turned, rate, step_s)
        self._turned_deg = _carried(self._turned_deg, rate, step_s * RAD_PER_DEG)
        self._elapsed_s += step_s
        if self._elapsed_s < RATE_WINDOW_S:
            return
        start, turned, turned_deg = self._start, self._turned, self._turned_deg
        self._start = self._turned = self._turned_deg = measured
        self._elapsed_s = 0.0
        predicted = _difference(turned, start)
        turn = _dot(predicted, predicted)
        if not turn >= RATE_MIN_TURN ** 2:
            return
        change = _difference(measured, start)
        share = min(max(_dot(change, predicted) / turn, RATE_CLIP[0]), RATE_CLIP[1])
        self._counted = min(self._counted + 1, RATE_WINDOWS)
        weight = 1.0 / self._counted
        self._mean += (share - self._mean) * weight
        misses = _difference(measured, turned), _difference(measured, turned_deg)
        self._misfit += (_dot(misses[0], misses[0]) - self._misfit) * weight
        self._misfit_deg += (_dot(misses[1], misses[1]) - self._misfit_deg) * weight
        if self._counted >= RATE_WINDOWS:
            self.agree = self._mean >= (RATE_DISAGREE if self.agree else RATE_AGREE)

    @property
    def scale(self) -> float | None:
        """The accelerometer's turning per the gyroscope's (None until RATE_WINDOWS counted)."""
        return self._mean if self._counted >= RATE_WINDOWS else None

    @property
    def looks_like_degrees(self) -> bool:
        """Whether the rates, disagreeing, would agree read as deg/s."""
        return (not self.agree and self.scale is not None
                and DEGREES_BETTER * self._misfit_deg < self._misfit)

    def problem(self) -> str:
        """Why the gyroscope and the accelerometer disagree, in words, the likely cause first
        (/diagnostics shortens long values); '' while they agree."""
        if self.agree or self.scale is None:
            return ''
        seen = (f"the accelerometer sees gravity's direction turn {self.scale:+.2f} times as far "
                'as the gyroscope turns it')
        if self.looks_like_degrees:
            return (f'the rates look like deg/s where rad/s are due: {seen}, and read as deg/s '
                    f'they predict it {DEGREES_BETTER:.0f} times better or more; every tilt '
                    'looks like an acceleration')
        return (f"its turning does not follow the accelerometer's: {seen}; are its axes the "
                "accelerometer's (one frame, the same signs) and its unit rad/s? (A multirotor "
                'in flight gives this too: its accelerometer reads thrust, not gravity)')


class GravityTracker:
    """Gravity's unit direction in the IMU frame (``up``: where the specific force points at
    rest), updated sample by sample in O(1)."""

    def __init__(self) -> None:
        self.bias: Vector = (0.0, 0.0, 0.0)
        """The gyroscope's bias about the tilt axes learnt so far (rad/s)."""
        self.rejected = 0
        """Samples whose specific force was not gravity (the robot accelerating)."""
        self._up: Vector | None = None
        self._filtered: Vector = (0.0, 0.0, 1.0)
        self._stamp_ns: int | None = None
        self._frame: str | None = None
        self._settling_s = 0.0
        self._rejecting_s = 0.0
        self._verdict: Vector | None = None
        self._gyro_seen = False
        self.rates = RateCheck()
        """Whether the gyroscope turns with the accelerometer (``problem()`` says why not)."""

    def restart(self) -> None:
        """Forget the direction, whether a gyroscope came and how it turned (a reset, a new
        sensor); the learnt bias stays, it is the gyroscope's."""
        self._up = self._stamp_ns = self._frame = self._verdict = None
        self._gyro_seen = False
        self.rates = RateCheck()

    def update(self, stamp_ns: int, force: Vector, gyro: Vector | None,
               frame_id: str = '') -> Vector | None:
        """One accelerometer sample (a finite specific force of a normal, non-zero norm) and
        its gyroscope sample: gravity's direction at that sample, or None when the specific
        force is not gravity (or the tracker has not settled). Without a gyroscope (none came
        since the start) nothing can tell an acceleration from a tilt: the specific force's own
        direction is returned, as every reading was levelled by before this tracker. Once one
        came, a sample without its rate (a NaN, a log's missing cell) is skipped: None, and the
        next sample carries on, or restarts after a gap."""
        measured = _unit(force)
        if gyro is None:
            return None if self._gyro_seen else measured
        self._gyro_seen = True
        if self._frame is not None and frame_id != self._frame:
            self.rates = RateCheck()  # another sensor: its own rates
        step_s = (None if self._stamp_ns is None or frame_id != self._frame
                  else (stamp_ns - self._stamp_ns) * 1e-9)
        if step_s == 0.0:
            return self._verdict  # the same instant again
        bias = self.bias
        rate = (gyro[0] - bias[0], gyro[1] - bias[1], gyro[2] - bias[2])
        carries = (step_s is not None and 0.0 < step_s <= MAX_STEP_S
                   and math.isfinite(math.hypot(*rate)))  # else a gap, or no gyroscope's rate
        self.rates.update(measured, rate if carries else None, step_s or 0.0)
        if not carries:
            self._start(stamp_ns, measured, frame_id)
            return None
        self._stamp_ns = stamp_ns
        share = min(1.0, step_s / LOWPASS_S)
        blend = _towards(_carried(self._filtered, rate, step_s), measured, share)
        if not math.hypot(*blend) > 0.0:  # the measurement turned exactly over
            self._start(stamp_ns, measured, frame_id)
            return None
        up = _carried(self._up, rate, step_s)
        self._filtered = filtered = _unit(blend)
        agreement = _dot(up, filtered)
        if agreement < math.cos(math.radians(GRAVITY_DEG)):
            self._up = up
            self.rejected += 1
            self._rejecting_s += step_s
            if self._rejecting_s > RESTART_S:
                self._start(stamp_ns, measured, frame_id)
            self._verdict = None
            return None
        self._rejecting_s = 0.0
        pull = min(1.0, step_s / CORRECTION_S)
        axis = _cross(up, filtered)  # rotating up about it moves it towards the measurement
        learn = step_s / (CORRECTION_S * BIAS_S)
        bias = (bias[0] + learn * axis[0], bias[1] + learn * axis[1], bias[2] + learn * axis[2])
        size = math.hypot(*bias)
        self.bias = (bias if size <= MAX_BIAS_RAD_S
                     else tuple(b * MAX_BIAS_RAD_S / size for b in bias))
        self._up = up = _unit(_towards(up, filtered, pull))
        self._settling_s += step_s
        self._verdict = up if self._settling_s >= SETTLE_S else None
        return self._verdict

    def _start(self, stamp_ns: int, measured: Vector, frame_id: str) -> None:
        self._up = self._filtered = measured
        self._stamp_ns, self._frame = stamp_ns, frame_id
        self._settling_s = self._rejecting_s = 0.0
        self._verdict = None


def _unit(vector: Vector) -> Vector:
    """The unit vector along a vector of a normal, non-zero norm (``math.hypot``: no
    underflow)."""
    x, y, z = vector
    norm = math.hypot(x, y, z)
    return x / norm, y / norm, z / norm


def _towards(a: Vector, b: Vector, share: float) -> Vector:
    """a + share (b - a)."""
    return (a[0] + share * (b[0] - a[0]), a[1] + share * (b[1] - a[1]),
            a[2] + share * (b[2] - a[2]))


def _dot(a: Vector, b: Vector) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _difference(a: Vector, b: Vector) -> Vector:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _cross(a: Vector, b: Vector) -> Vector:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _carried(vector: Vector, rate: Vector, step_s: float) -> Vector:
    """A direction fixed in the world, seen from a body turning at ``rate`` (rad/s, body frame)
    for ``step_s``: rotated by -rate x step (Rodrigues' formula, exact for a constant rate)."""
    wx, wy, wz = rate
    angle = math.hypot(wx, wy, wz) * step_s
    if not angle > 0.0:
        return vector
    scale = step_s / angle
    kx, ky, kz = -wx * scale, -wy * scale, -wz * scale  # the unit axis of -rate
    vx, vy, vz = vector
    cos, sin = math.cos(angle), math.sin(angle)
    dot = (kx * vx + ky * vy + kz * vz) * (1.0 - cos)
    cx, cy, cz = ky * vz - kz * vy, kz * vx - kx * vz, kx * vy - ky * vx
    return (vx * cos + cx * sin + kx * dot, vy * cos + cy * sin + ky * dot,
            vz * cos + cz * sin + kz * dot)


__all__ = ['GRAVITY_DEG', 'GravityTracker', 'RateCheck']
