# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Orientation trajectories and the earth's field for the simulated sensor, demo and benchmarks.

A magnetometer calibration is only as good as the orientations it saw, so the simulator moves the
sensor the way people and robots do: a hand tumbling the board (``tumble``), a ground robot
turning in place with a little tilt (``yaw``), a board lying on the bench (``still``), a hand
turning the board from pose to pose and holding each still for a moment (``poses``: what aligning
the magnetometer to gravity needs, see ``calibration.alignment``), or a ground robot turning only
as commanded on ``cmd_vel`` (``cmd_vel``, closing the loop with the calibrator's
``~/rotate_and_calibrate``). Every trajectory is deterministic for a seed (and, for ``cmd_vel``,
its commands) so tests and benchmarks are repeatable.

The inertial sensors need more than the orientation: ``state(t)`` gives the orientation, the body
angular rate (what a gyroscope measures) and the linear acceleration (what an accelerometer adds to
gravity) of one consistent motion, so a new motion (a robot following ``cmd_vel``, say) plugs into
the simulator by implementing that one method.

Conventions: world frame ENU (x east, y north, z up); ``orientation(t)`` is the rotation matrix
world<-body, so a world vector ``v`` reads ``R.T @ v`` in the body frame; angular velocity in the
body frame (rad/s), linear acceleration in the world frame (m/s^2, gravity excluded).
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
import math
import threading
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation
else:

    class _LazyRotation:
        """scipy's Rotation, imported on first use: scipy.spatial is heavy to import, and a node
        that never simulates (a driver on real hardware) never needs it."""

        def __getattr__(self, name: str) -> object:
            from scipy.spatial.transform import Rotation

            return getattr(Rotation, name)

    Rotation = _LazyRotation()

TRAJECTORY_KINDS = ('tumble', 'yaw', 'still', 'poses', 'cmd_vel')
ZERO3 = np.zeros(3)
ZERO3.setflags(write=False)


def earth_field(strength: float, inclination_deg: float, declination_deg: float = 0.0
                ) -> np.ndarray:
    """World-frame (ENU) earth field: ``F cos I`` towards magnetic north, ``F sin I`` downwards.

    Positive inclination dips the field below the horizon (northern hemisphere), so the up
    component is ``-F sin I``; magnetic north lies ``declination_deg`` east of true north (y).
    Units are those of ``strength``.
    """
    strength = float(strength)
    inclination_deg = float(inclination_deg)
    if not math.isfinite(strength) or strength < 0.0:
        raise ValueError(f'field strength must be finite and >= 0, got {strength}')
    if not math.isfinite(inclination_deg) or abs(inclination_deg) > 90.0:
        raise ValueError(f'inclination must be within [-90, 90] degrees, got {inclination_deg}')
    if not math.isfinite(float(declination_deg)):
        raise ValueError(f'declination must be finite, got {declination_deg}')
    inclination = math.radians(inclination_deg)
    declination = math.radians(float(declination_deg))
    horizontal = strength * math.cos(inclination)
    return np.array([horizontal * math.sin(declination), horizontal * math.cos(declination),
                     -strength * math.sin(inclination)])


@dataclass(frozen=True)
class MotionState:
    """The board's motion at one instant.

    ``rotation``: (3,3) world<-body; ``angular_velocity``: (3,) body frame, rad/s;
    ``linear_acceleration``: (3,) world frame, m/s^2, gravity excluded.
    """

    rotation: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray


class Trajectory:
    """A body motion as a function of time (seconds, t >= 0).

    Subclasses give ``rotations``; those that move also override ``state`` (the simulator calls
    it once per inertial sample, so it should be cheap for a single time).
    """

    kind: str = ''

    def rotations(self, times: np.ndarray) -> Rotation:
        """World<-body rotations at ``times`` (1-D array, seconds)."""
        raise NotImplementedError

    def orientation(self, t: float) -> np.ndarray:
        """World<-body rotation matrix (3,3) at time ``t``."""
        return self.rotations(np.array([t])).as_matrix()[0]

    def orientations(self, times: np.ndarray) -> np.ndarray:
        """World<-body rotation matrices (n,3,3) at ``times``."""
        return self.rotations(times).as_matrix().reshape(-1, 3, 3)

    def state(self, t: float) -> MotionState:
        """Orientation, body angular velocity and linear acceleration at time ``t``."""
        return MotionState(self.orientation(t), ZERO3, ZERO3)

    def angular_velocity(self, t: float) -> np.ndarray:
        """Body-frame angular velocity (3,) in rad/s at time ``t``."""
        return self.state(t).angular_velocity

    def linear_acceleration(self, t: float) -> np.ndarray:
        """World-frame linear acceleration (3,) in m/s^2 at time ``t`` (gravity excluded)."""
        return self.state(t).linear_acceleration


def _checked_time(t: float) -> float:
    """One time, checked (the per-sample path: no array round trip)."""
    t = float(t)
    if not math.isfinite(t) or t < 0.0:
        raise ValueError('trajectory times must be finite and >= 0 seconds')
    return t


def _checked_times(times: np.ndarray) -> np.ndarray:
    times = np.atleast_1d(np.asarray(times, dtype=float))
    if times.ndim != 1:
        raise ValueError(f'times must be a scalar or a 1-D array, got shape {times.shape}')
    if not np.all(np.isfinite(times)) or np.any(times < 0.0):
        raise ValueError('trajectory times must be finite and >= 0 seconds')
    return times


class StillTrajectory(Trajectory):
    """A board lying on the bench: level within a degree, heading chosen by the seed."""

    kind = 'still'

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng([seed, 3])
        heading = rng.uniform(-math.pi, math.pi)
        roll, pitch = rng.normal(0.0, math.radians(0.5), size=2)
        self._quat = Rotation.from_euler('ZYX', [heading, pitch, roll]).as_quat()
        self._state = MotionState(Rotation.from_quat(self._quat).as_matrix(), ZERO3, ZERO3)

    def rotations(self, times: np.ndarray) -> Rotation:
        times = _checked_times(times)
        return Rotation.from_quat(np.tile(self._quat, (len(times), 1)))

    def state(self, t: float) -> MotionState:
        _checked_time(t)
        return self._state


class YawTrajectory(Trajectory):
    """A ground robot turning in place: steady yaw rate, slow speed changes, a few degrees of tilt.

    Yaw covers full circles every ~10-20 s; roll and pitch wander within about +-4 degrees (uneven
    floor, suspension), which is what a planar (2-D) calibration sees on a real robot.
    """

    kind = 'yaw'

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng([seed, 2])
        self._yaw0 = rng.uniform(-math.pi, math.pi)
        self._yaw_rate = rng.choice([-1.0, 1.0]) * rng.uniform(0.35, 0.6)  # rad/s
        # Speed changes: two slow sinusoids on the yaw angle (amplitudes in rad).
        self._yaw_mod = rng.uniform(0.2, 0.5, size=2)
        self._yaw_mod_freq = rng.uniform(0.03, 0.12, size=2) * 2.0 * math.pi
        self._yaw_mod_phase = rng.uniform(0.0, 2.0 * math.pi, size=2)
        # Tilt: each of roll and pitch is a sum of two sinusoids, about 2-4 degrees overall.
        self._tilt_amp = np.radians(rng.uniform(1.0, 2.0, size=(2, 2)))
        self._tilt_freq = rng.uniform(0.05, 0.4, size=(2, 2)) * 2.0 * math.pi
        self._tilt_phase = rng.uniform(0.0, 2.0 * math.pi, size=(2, 2))

    def rotations(self, times: np.ndarray) -> Rotation:
        t = _checked_times(times)
        yaw = self._yaw0 + self._yaw_rate * t
        yaw = yaw + np.sum(
            self._yaw_mod * np.sin(self._yaw_mod_freq * t[:, None] + self._yaw_mod_phase), axis=1
        )
        tilt = np.sum(
            self._tilt_amp * np.sin(self._tilt_freq * t[:, None, None] + self._tilt_phase), axis=2
        )
        return Rotation.from_euler('ZYX', np.column_stack([yaw, tilt[:, 1], tilt[:, 0]]))

    def state(self, t: float) -> MotionState:
        """Analytic: Z-Y-X Euler angles and their rates mapped to the body rate; the IMU sits on
        the turning axis, so there is no linear acceleration."""
        t = _checked_time(t)
        mod = self._yaw_mod_freq * t + self._yaw_mod_phase
        yaw = self._yaw0 + self._yaw_rate * t + float(np.sum(self._yaw_mod * np.sin(mod)))
        yaw_rate = self._yaw_rate + float(np.sum(self._yaw_mod * self._yaw_mod_freq * np.cos(mod)))
        phase = self._tilt_freq * t + self._tilt_phase
        roll, pitch = np.sum(self._tilt_amp * np.sin(phase), axis=1)
        roll_rate, pitch_rate = np.sum(self._tilt_amp * self._tilt_freq * np.cos(phase), axis=1)
        return MotionState(
            _zyx_matrix(yaw, pitch, roll),
            _zyx_body_rate(yaw_rate, pitch, pitch_rate, roll, roll_rate),
            ZERO3,
        )


def _zyx_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll), as scipy's ``from_euler('ZYX', ...)``."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def _zyx_body_rate(
    yaw_rate: float, pitch: float, pitch_rate: float, roll: float, roll_rate: float
) -> np.ndarray:
    """Body angular velocity of R = Rz(yaw) Ry(pitch) Rx(roll) from the Euler angle rates."""
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([
        roll_rate - yaw_rate * sp,
        pitch_rate * cr + yaw_rate * cp * sr,
        -pitch_rate * sr + yaw_rate * cp * cr,
    ])


class TumbleTrajectory(Trajectory):
    """A hand tumbling the board: body angular velocity is low-pass filtered white noise.

    Each body axis's rate is white noise through two cascaded first-order low-passes (time constant
    ``correlation_s``), scaled to ``rate_std`` rad/s per axis; peaks reach several rad/s, and the
    random walk on SO(3) visits every orientation within 30-60 s. The rate is integrated exactly
    on a 25 Hz knot grid (piecewise-constant rate between knots, so a gyroscope sampling it sees
    the exact rate), extended lazily and forgotten after ``retain_s`` seconds so a long-running
    simulator stays bounded in memory. The hand also moves the board a few centimetres at
    0.2-1 Hz (three sinusoids per axis): linear acceleration of about 1 m/s^2 RMS.
    """

    kind = 'tumble'
    KNOT_HZ = 25.0
    CHUNK = 250  # knots generated per extension (10 s)

    def __init__(
        self,
        seed: int = 0,
        rate_std: float = 1.4,
        correlation_s: float = 0.35,
        retain_s: float = 3600.0,
    ) -> None:
        self._rng = np.random.default_rng([seed, 1])
        self._dt = 1.0 / self.KNOT_HZ
        self._alpha = math.exp(-self._dt / correlation_s)
        a = self._alpha
        # Stationary variance of the two-stage filter with unit input: (1-a)^4 (1+a^2) / (1-a^2)^3.
        gain = math.sqrt((1 - a) ** 4 * (1 + a * a) / (1 - a * a) ** 3)
        self._input_std = rate_std / gain
        self._stage1 = self._rng.normal(0.0, rate_std, 3)
        self._stage2 = self._stage1.copy()
        self._retain_knots = max(int(retain_s * self.KNOT_HZ), 2 * self.CHUNK)
        self._first = 0  # index of the first retained knot
        self._quats = Rotation.random(random_state=self._rng).as_quat()[None, :]
        self._rotvecs = np.empty((0, 3))  # rotvec from knot k to knot k+1 (body frame)
        # Translation (its own random stream, so the orientations do not depend on it).
        shake = np.random.default_rng([seed, 4])
        self._shake_amp = shake.uniform(0.01, 0.04, size=(3, 3))  # metres, axis x component
        self._shake_freq = shake.uniform(0.2, 1.0, size=(3, 3)) * 2.0 * math.pi
        self._shake_phase = shake.uniform(0.0, 2.0 * math.pi, size=(3, 3))

    def _extend(self) -> None:
        steps = np.empty((self.CHUNK, 3))
        a = self._alpha
        noise = self._rng.normal(0.0, self._input_std, (self.CHUNK, 3))
        for i in range(self.CHUNK):
            self._stage1 = a * self._stage1 + (1 - a) * noise[i]
            self._stage2 = a * self._stage2 + (1 - a) * self._stage1
            steps[i] = self._stage2 * self._dt
        increments = Rotation.from_rotvec(steps)
        quats = np.empty((self.CHUNK, 4))
        current = Rotation.from_quat(self._quats[-1])
        for i in range(self.CHUNK):
            current = current * increments[i]
            quats[i] = current.as_quat()
        self._quats = np.vstack([self._quats, quats])
        self._rotvecs = np.vstack([self._rotvecs, steps])
        surplus = len(self._rotvecs) - self._retain_knots
        if surplus >= self.CHUNK:
            self._quats = self._quats[surplus:]
            self._rotvecs = self._rotvecs[surplus:]
            self._first += surplus

    def rotations(self, times: np.ndarray) -> Rotation:
        times = _checked_times(times)
        if len(times) == 0:
            return Rotation.from_quat(np.empty((0, 4)))
        position = times * self.KNOT_HZ
        knot = np.floor(position).astype(np.int64)
        while knot.max() >= self._first + len(self._rotvecs):
            self._extend()
        if knot.min() < self._first:
            raise ValueError(
                f'tumble trajectory keeps only the last '
                f'{self._retain_knots / self.KNOT_HZ:.0f} s; '
                f't={times.min():.2f} s is no longer available'
            )
        local = knot - self._first
        fraction = (position - knot)[:, None]
        return Rotation.from_quat(self._quats[local]) * Rotation.from_rotvec(
            fraction * self._rotvecs[local]
        )

    def position(self, t: float) -> np.ndarray:
        """World-frame displacement (3,) in metres of the hand's translation at time ``t``."""
        t = _checked_time(t)
        return np.sum(self._shake_amp * np.sin(self._shake_freq * t + self._shake_phase), axis=1)

    def state(self, t: float) -> MotionState:
        """Plain float arithmetic: called once per simulated sample, up to 1 kHz."""
        t = _checked_time(t)
        position = t * self.KNOT_HZ
        knot = math.floor(position)
        while knot >= self._first + len(self._rotvecs):
            self._extend()
        if knot < self._first:
            self.rotations(np.array([t]))  # raises the 'no longer available' error
        local = knot - self._first
        step = self._rotvecs[local].tolist()
        quat = _quat_multiply(self._quats[local].tolist(),
                              _rotvec_quat([(position - knot) * v for v in step]))
        omega = np.array(step) * self.KNOT_HZ  # constant between knots, body frame
        phase = self._shake_freq * t + self._shake_phase
        acceleration = -np.sum(self._shake_amp * self._shake_freq**2 * np.sin(phase), axis=1)
        return MotionState(_quat_matrix(quat), omega, acceleration)


class PosesTrajectory(Trajectory):
    """A hand turning the board from pose to pose and holding each one still.

    Poses are uniformly random orientations; each is held for ``hold_s``, then the board turns
    to the next about a fixed body axis in ``move_s`` with a quintic (minimum-jerk) profile, so
    rate and acceleration start and end at zero, while the hand carries it a few centimetres the
    same way. Still, it measures exactly gravity; moving, it turns at up to ~3 rad/s. This is
    the static-attitude procedure of accelerometer and joint calibrations (ArduPilot's six-pose
    accelerometer calibration; MAG.I.C.AL., Papafotis & Sotiriadis 2019).
    """

    kind = 'poses'
    CACHE = 64  # poses kept for random access

    def __init__(self, seed: int = 0, hold_s: float = 0.8, move_s: float = 1.2) -> None:
        self._seed = int(seed)
        self._hold = float(hold_s)
        self._move = float(move_s)
        self._period = self._hold + self._move
        self._poses: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _pose(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(quaternion of pose ``index``, body rotation vector to the next, displacement)."""
        cached = self._poses.get(index)
        if cached is None:
            here = Rotation.random(random_state=np.random.default_rng([self._seed, 5, index]))
            after = Rotation.random(random_state=np.random.default_rng([self._seed, 5, index + 1]))
            shift = np.random.default_rng([self._seed, 6, index]).normal(0.0, 0.03, 3)
            cached = (here.as_quat(), (here.inv() * after).as_rotvec(), shift)
            if len(self._poses) >= self.CACHE:
                self._poses.clear()
            self._poses[index] = cached
        return cached

    def _phase(self, t: float) -> tuple[int, float]:
        """Pose index and the move's progress tau in [0, 1] (0 while holding)."""
        index = math.floor(t / self._period)
        into = t - index * self._period - self._hold
        return index, (into / self._move if into > 0.0 else 0.0)

    @staticmethod
    def _profile(tau: float) -> tuple[float, float, float]:
        """Minimum-jerk s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 and its first two derivatives."""
        return (tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau),
                30.0 * tau * tau * (1.0 - tau) ** 2,
                60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau))

    def rotations(self, times: np.ndarray) -> Rotation:
        times = _checked_times(times)
        quats = np.empty((len(times), 4))
        rotvecs = np.empty((len(times), 3))
        for i, t in enumerate(times.tolist()):
            index, tau = self._phase(t)
            quat, rotvec, _ = self._pose(index)
            quats[i] = quat
            rotvecs[i] = self._profile(tau)[0] * rotvec
        return Rotation.from_quat(quats) * Rotation.from_rotvec(rotvecs)

    def state(self, t: float) -> MotionState:
        t = _checked_time(t)
        index, tau = self._phase(t)
        quat, rotvec, shift = self._pose(index)
        position, rate, acceleration = self._profile(tau)
        step = _rotvec_quat([position * v for v in rotvec.tolist()])
        return MotionState(_quat_matrix(_quat_multiply(quat.tolist(), step)),
                           rotvec * (rate / self._move), shift * (acceleration / self._move**2))

    def holding(self, t: float) -> bool:
        """Whether the board is held still at time ``t``."""
        return self._phase(_checked_time(t))[1] == 0.0


def _rotvec_quat(rotvec) -> tuple[float, float, float, float]:
    """Rotation vector -> unit quaternion (x, y, z, w), scipy's order."""
    x, y, z = rotvec
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return 0.5 * x, 0.5 * y, 0.5 * z, 1.0
    scale = math.sin(0.5 * angle) / angle
    return x * scale, y * scale, z * scale, math.cos(0.5 * angle)


def _quat_multiply(a, b) -> tuple[float, float, float, float]:
    """Hamilton product a * b of (x, y, z, w) quaternions: rotation b, then a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + bw * ax + ay * bz - az * by,
            aw * by + bw * ay + az * bx - ax * bz,
            aw * bz + bw * az + ax * by - ay * bx,
            aw * bw - ax * bx - ay * by - az * bz)


def _quat_matrix(quat) -> np.ndarray:
    x, y, z, w = quat
    norm = 1.0 / math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x * norm, y * norm, z * norm, w * norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@dataclass(frozen=True)
class DriveCurrent:
    """The battery current a differential-drive robot draws: ``idle_a`` with the wheels still
    (computer, sensors, motor drivers), rising linearly with the wheels' mean absolute speed to
    ``full_a`` with both wheels at the robot's top speed.

    A DC motor's current follows its torque; on flat ground at steady speed that torque is
    rolling resistance and friction, which grow with speed, so current rises with wheel speed
    (the +8-9 uT on a ground robot's |B| correlated with wheel speed in
    manankharwar/fusioncore#93). A turn in place spins both wheels at ``yaw_rate *
    track_width_m / 2`` in opposite directions, so it draws current too. Not modelled:
    acceleration torque, slopes, skid-steer scrubbing and a battery's voltage sag.
    """

    idle_a: float = 0.5
    full_a: float = 5.0
    track_width_m: float = 0.3
    NOMINAL_V = 12.0
    RESISTANCE_OHM = 0.05
    """The pack: 12 V nominal with a 0.05 ohm internal resistance (a voltage to publish; the
    sag does not change the current)."""

    def voltage(self, current: float) -> float:
        """The pack's voltage (V) while it supplies ``current`` A."""
        return self.NOMINAL_V - self.RESISTANCE_OHM * current

    def current(self, speed: float, yaw_rate: float, top_speed: float) -> float:
        """Amperes drawn at ``speed`` m/s (forward, either sign) and ``yaw_rate`` rad/s, the
        wheels' top speed ``top_speed`` m/s."""
        half_track = 0.5 * self.track_width_m * yaw_rate
        wheels = 0.5 * (abs(speed - half_track) + abs(speed + half_track))
        return self.idle_a + (self.full_a - self.idle_a) * wheels / top_speed


class CmdVelTrajectory(Trajectory):
    """A ground robot that drives and turns only as commanded (``cmd_vel``'s linear x and
    angular z).

    ``command(yaw_rate, t, speed)`` sets the target yaw rate and forward speed at simulated time
    ``t``; each follows its target within its limits (``max_rate`` rad/s and
    ``max_acceleration`` rad/s^2; ``max_speed`` m/s and ``max_linear_acceleration`` m/s^2), as a
    base's velocity controller does, and falls back to zero when no command came for
    ``command_timeout`` seconds, as bases with a command timeout do (ros2_control's
    diff_drive_controller stops after 0.5 s by default): a commander that dies stops the robot
    only if it kept re-sending while alive. Nothing moves without commands.

    The IMU sits on the turning axis: driving adds the forward acceleration and the centripetal
    ``speed * yaw_rate`` (body y) to what the accelerometer measures; the earth's field is the
    same everywhere the robot drives, so only the heading changes what the magnetometer reads.
    The battery current (``battery_current``) follows the motion through ``drive``
    (``DriveCurrent``).

    The tilt belongs to the floor under the wheels, so it is a function of the heading alone: roll
    and pitch are sums of the first three harmonics of yaw (a slope, then bumps) with seeded
    phases, peaking at ``wobble_deg``. A standing robot never wobbles; a turning one sees the
    few degrees of tilt a planar calibration must tolerate.

    Commands never change the past: one takes effect at ``t`` or at the latest time a state was
    read, whichever is later, so everything the simulated sensors measured stays true (their
    reads come nearly, not strictly, in time order). Yaw is integrated exactly, piecewise
    (constant acceleration, then constant rate) from one command to the next. Thread-safe:
    commands come from a ROS callback while the simulator's thread reads states.
    """

    kind = 'cmd_vel'
    RETAIN_S = 60.0
    """Commands older than this (before the latest state read) are forgotten: bounded memory."""
    HARMONICS = 3

    def __init__(
        self,
        seed: int = 0,
        max_rate: float = 1.0,
        max_acceleration: float = 1.0,
        wobble_deg: float = 2.0,
        command_timeout: float = 0.5,
        max_speed: float = 0.5,
        max_linear_acceleration: float = 1.0,
        drive: DriveCurrent | None = None,
    ) -> None:
        drive = DriveCurrent() if drive is None else drive
        problems = cmd_vel_problems(max_rate, max_acceleration, wobble_deg, command_timeout,
                                    max_speed, max_linear_acceleration, drive)
        if problems:
            raise ValueError('invalid cmd_vel motion: ' + '; '.join(problems))
        self.max_rate = float(max_rate)
        self.max_acceleration = float(max_acceleration)
        self.command_timeout = float(command_timeout)
        self.max_speed = float(max_speed)
        self.max_linear_acceleration = float(max_linear_acceleration)
        self.drive = drive
        rng = np.random.default_rng([seed, 5])
        yaw0 = float(rng.uniform(-math.pi, math.pi))
        orders = np.arange(1, self.HARMONICS + 1)
        amplitudes = rng.uniform(0.3, 1.0, size=(2, self.HARMONICS)) / orders
        phases = rng.uniform(0.0, 2.0 * math.pi, size=(2, self.HARMONICS))
        grid = np.linspace(0.0, 2.0 * math.pi, 721)
        tilt = np.sum(amplitudes[:, None, :] * np.sin(orders * grid[:, None] + phases[:, None, :]),
                      axis=2)
        peak = float(np.max(np.hypot(tilt[0], tilt[1])))
        self._tilt_amplitudes = (amplitudes * math.radians(float(wobble_deg)) / peak).tolist()
        self._tilt_phases = phases.tolist()
        self._lock = threading.Lock()
        # Knots: (time, yaw, yaw rate, target rate, time the targets lapse to zero, speed,
        # target speed).
        self._knots: list[tuple[float, float, float, float, float, float, float]] = [
            (0.0, yaw0, 0.0, 0.0, math.inf, 0.0, 0.0)]
        self._knot_times = [0.0]
        self._latest = 0.0  # the latest time a state was read

    def command(self, yaw_rate: float, t: float, speed: float = 0.0) -> float:
        """Turn at ``yaw_rate`` rad/s (positive: counter-clockwise seen from above, REP-103)
        and drive forward at ``speed`` m/s (negative: backwards) from time ``t``; a non-finite
        value is a stop of that motion. Returns the yaw-rate target after clamping."""
        t = _checked_time(t)
        target = _clamped(yaw_rate, self.max_rate)
        target_speed = _clamped(speed, self.max_speed)
        with self._lock:
            start = max(t, self._latest, self._knot_times[-1])
            yaw, rate, now_speed, _ = self._evolve(self._knots[-1], start)
            self._knots.append((start, yaw, rate, target, start + self.command_timeout,
                                now_speed, target_speed))
            self._knot_times.append(start)
            old = bisect_right(self._knot_times, self._latest - self.RETAIN_S) - 1
            if old > 0:
                del self._knots[:old], self._knot_times[:old]
        return target

    def yaw_and_rate(self, t: float) -> tuple[float, float]:
        """Yaw (rad, unwrapped) and yaw rate (rad/s) at time ``t``."""
        yaw, rate, _, _ = self._motion(t)
        return yaw, rate

    def speed(self, t: float) -> float:
        """Forward speed (m/s) at time ``t``."""
        return self._motion(t)[2]

    def battery_current(self, t: float) -> float:
        """The battery current (A) the robot draws at time ``t`` (``DriveCurrent``)."""
        _, rate, speed, _ = self._motion(t)
        return self.drive.current(speed, rate, self.max_speed)

    def _motion(self, t: float) -> tuple[float, float, float, float]:
        """(yaw, yaw rate, speed, forward acceleration) at time ``t``."""
        t = _checked_time(t)
        with self._lock:
            self._latest = max(self._latest, t)
            index = max(bisect_right(self._knot_times, t) - 1, 0)
            return self._evolve(self._knots[index], t)

    def _evolve(self, knot: tuple[float, float, float, float, float, float, float], end: float
                ) -> tuple[float, float, float, float]:
        start, yaw, rate, target, lapse, speed, target_speed = knot
        end = max(end, start)
        if lapse < end:  # no command for command_timeout: the base stops by itself
            yaw, rate = self._ramp(yaw, rate, target, lapse - start)
            speed, _ = _follow(speed, target_speed, self.max_linear_acceleration, lapse - start)
            start, target, target_speed = lapse, 0.0, 0.0
        yaw, rate = self._ramp(yaw, rate, target, end - start)
        speed, acceleration = _follow(speed, target_speed, self.max_linear_acceleration,
                                      end - start)
        return yaw, rate, speed, acceleration

    def _ramp(self, yaw: float, rate: float, target: float, dt: float) -> tuple[float, float]:
        """Rate towards ``target`` at the acceleration limit for ``dt`` s; exact yaw."""
        change = target - rate
        ramp_s = abs(change) / self.max_acceleration
        if dt <= ramp_s:
            acceleration = math.copysign(self.max_acceleration, change)
            return yaw + rate * dt + 0.5 * acceleration * dt * dt, rate + acceleration * dt
        return yaw + 0.5 * (rate + target) * ramp_s + target * (dt - ramp_s), target

    def _tilt(self, yaw: float) -> tuple[float, float, float, float]:
        """(roll, pitch) and their derivatives by yaw."""
        values = []
        for amplitudes, phases in zip(self._tilt_amplitudes, self._tilt_phases, strict=True):
            angle = slope = 0.0
            for order, (amplitude, phase) in enumerate(zip(amplitudes, phases, strict=True), 1):
                angle += amplitude * math.sin(order * yaw + phase)
                slope += order * amplitude * math.cos(order * yaw + phase)
            values += [angle, slope]
        return values[0], values[1], values[2], values[3]

    def state(self, t: float) -> MotionState:
        """Plain float arithmetic: the simulator calls it once per sample."""
        yaw, yaw_rate, speed, forward = self._motion(t)
        roll, roll_slope, pitch, pitch_slope = self._tilt(yaw)
        rotation = _zyx_matrix(yaw, pitch, roll)
        moving = speed != 0.0 or forward != 0.0
        return MotionState(
            rotation,
            _zyx_body_rate(yaw_rate, pitch, yaw_rate * pitch_slope, roll, yaw_rate * roll_slope),
            rotation @ np.array([forward, speed * yaw_rate, 0.0]) if moving else ZERO3,
        )

    def orientation(self, t: float) -> np.ndarray:
        return self.state(t).rotation

    def rotations(self, times: np.ndarray) -> Rotation:
        times = _checked_times(times)
        if len(times) == 0:
            return Rotation.from_quat(np.empty((0, 4)))
        return Rotation.from_matrix(np.array([self.state(t).rotation for t in times]))


def _clamped(value: object, limit: float) -> float:
    """A commanded velocity within ±``limit``; anything not a finite number is a stop."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        return 0.0
    return min(max(value, -limit), limit) if math.isfinite(value) else 0.0


def _follow(value: float, target: float, limit: float, dt: float) -> tuple[float, float]:
    """(value, its rate of change) after ``dt`` s of moving towards ``target`` at ``limit``."""
    change = target - value
    if abs(change) <= limit * dt:
        return target, 0.0
    slope = math.copysign(limit, change)
    return value + slope * dt, slope


def cmd_vel_problems(max_rate: float, max_acceleration: float, wobble_deg: float,
                     command_timeout: float, max_speed: float = 0.5,
                     max_linear_acceleration: float = 1.0,
                     drive: DriveCurrent | None = None) -> list[str]:
    """Every problem with a ``cmd_vel`` motion's limits and drive current (empty when usable)."""
    problems = []
    drive = DriveCurrent() if drive is None else drive
    for name, value, low, high, unit in (
        ('max_rate', max_rate, 0.0, 10.0, 'rad/s'),
        ('max_acceleration', max_acceleration, 0.0, 100.0, 'rad/s^2'),
        ('command_timeout', command_timeout, 0.0, 60.0, 's'),
        ('max_speed', max_speed, 0.0, 20.0, 'm/s'),
        ('max_linear_acceleration', max_linear_acceleration, 0.0, 100.0, 'm/s^2'),
        ('track_width', drive.track_width_m, 0.0, 10.0, 'm'),
    ):
        if not (_real(value) and low < value <= high):
            problems.append(f'{name} must be in ({low:g}, {high:g}] {unit}, got {value!r}')
    if not (_real(wobble_deg) and 0.0 <= wobble_deg <= 20.0):
        problems.append(f'wobble_deg must be in [0, 20] degrees, got {wobble_deg!r}')
    idle, full = drive.idle_a, drive.full_a
    if not (_real(idle) and 0.0 <= idle <= 1000.0):
        problems.append(f'idle_current_a must be in [0, 1000] A, got {idle!r}')
    elif not (_real(full) and idle <= full <= 1000.0):
        problems.append(f'full_current_a must be in [idle_current_a, 1000] A (the current at '
                        f'top speed includes the idle current), got {full!r} with idle '
                        f'{idle!r}')
    return problems


def _real(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(
        value)


def make_trajectory(kind: str, seed: int = 0) -> Trajectory:
    """The trajectory named ``kind`` (TRAJECTORY_KINDS), deterministic for ``seed``; ``cmd_vel``
    with its default limits (standing until commanded)."""
    factories = {'tumble': TumbleTrajectory, 'yaw': YawTrajectory, 'still': StillTrajectory,
                 'poses': PosesTrajectory, 'cmd_vel': CmdVelTrajectory}
    if kind not in factories:
        raise ValueError(f"unknown motion {kind!r}; expected one of {', '.join(TRAJECTORY_KINDS)}")
    return factories[kind](seed=int(seed))


def body_field_samples(
    kind: str,
    n: int,
    rate_hz: float,
    strength: float,
    inclination_deg: float,
    seed: int = 0,
) -> np.ndarray:
    """True body-frame earth field (n,3) at ``rate_hz`` from t=0 along trajectory ``kind``."""
    n = int(n)
    rate_hz = float(rate_hz)
    if n < 0:
        raise ValueError(f'sample count must be >= 0, got {n}')
    if not math.isfinite(rate_hz) or rate_hz <= 0.0:
        raise ValueError(f'rate_hz must be finite and > 0, got {rate_hz}')
    field = earth_field(strength, inclination_deg)
    trajectory = make_trajectory(kind, seed)
    times = np.arange(n) / rate_hz
    out = np.empty((n, 3))
    chunk = 100_000  # time-ordered chunks keep the tumble knot window bounded
    for start in range(0, n, chunk):
        rotations = trajectory.rotations(times[start:start + chunk])
        out[start:start + chunk] = rotations.inv().apply(field)
    return out


@dataclass(frozen=True)
class Leg:
    """One leg of a driven course: ``speed`` m/s forward and ``yaw_rate`` rad/s for
    ``duration_s`` seconds (both zero: a stop)."""

    duration_s: float
    speed: float = 0.0
    yaw_rate: float = 0.0


GROUND_COURSE = (
    Leg(5.0),                    # standing, motors idle
    Leg(14.0, yaw_rate=0.5),     # a turn in place, about a circle
    Leg(15.0, speed=0.5),        # straight at top speed
    Leg(3.0),
    Leg(4.0, yaw_rate=0.8),      # turn left, about half a circle
    Leg(14.0, speed=0.25),       # straight, half speed
    Leg(2.0),
    Leg(3.0, yaw_rate=-0.6),     # turn right
    Leg(12.0, speed=0.4),
    Leg(4.0),
    Leg(10.0, yaw_rate=-0.7),    # a turn in place the other way, more than a circle
    Leg(14.0, speed=0.15),       # crawling
    Leg(3.0, yaw_rate=1.0),
    Leg(16.0, speed=0.5),
    Leg(5.0),
    Leg(6.0, yaw_rate=0.4),
    Leg(10.0, speed=0.3),
    Leg(2.0, yaw_rate=-0.9),
    Leg(18.0, speed=0.45),
    Leg(5.0, yaw_rate=0.6),
    Leg(15.0),                   # parked, motors idle, still warming
)
"""The benchmark's three-minute ground course: straight legs at speeds from a crawl to the top
speed at many headings, turns in place both ways, and stops; what a calibrator must see to
tell a current's field (it grows with speed, fixed to the robot) from the hard iron and the
earth's field (it turns with the heading)."""


QUICK_PROCEDURE = (
    Leg(2.0),
    Leg(3.0, speed=0.2), Leg(2.0), Leg(3.0, speed=-0.2), Leg(2.0),
    Leg(3.0, speed=0.5), Leg(2.0), Leg(3.0, speed=-0.5), Leg(2.0),
    Leg(3.0, speed=0.35), Leg(2.0), Leg(3.0, speed=-0.35), Leg(2.0),
)
"""``~/learn_compensation`` on the floor: straight ahead and back at three speeds, stopping
between (it ends where it started, facing the same way): the current steps while the heading
holds, which the gyroscope tells the magnetometer (``fit/compensation.py`` gyro_pairs)."""


class CourseDriver:
    """The commands of a course of ``Leg``s: ``command_at(t)`` gives (speed, yaw rate) at
    ``t`` seconds from its start (zero after its end), for a teleop re-sending them on cmd_vel
    or a simulation calling ``CmdVelTrajectory.command``."""

    def __init__(self, legs: tuple[Leg, ...] = GROUND_COURSE) -> None:
        if not legs or any(not (math.isfinite(leg.duration_s) and leg.duration_s > 0.0)
                           for leg in legs):
            raise ValueError('a course needs at least one leg, each of a finite duration > 0 s')
        self.legs = tuple(legs)
        self._ends = np.cumsum([leg.duration_s for leg in legs]).tolist()

    @property
    def duration_s(self) -> float:
        return self._ends[-1]

    def command_at(self, t: float) -> tuple[float, float]:
        """(speed m/s, yaw rate rad/s) commanded at ``t`` seconds into the course."""
        index = bisect_right(self._ends, _checked_time(t))
        if index >= len(self.legs):
            return 0.0, 0.0
        leg = self.legs[index]
        return leg.speed, leg.yaw_rate


# -- motions of ordinary use (issue #44): a wrist, a drone, a board carried along a path -------
#
# Each is a pure function of time, seeded where random: smooth sums of sinusoids mapped onto
# rotation vectors, so the body rate is analytic (the right Jacobian of SO(3), below) and a
# gyroscope sampling it sees the true rate of the orientation path. They are not in
# ``TRAJECTORY_KINDS`` (the node's ``sim.motion`` and the demo keep their choices): construct
# them and hand them to ``board.BoardModel(config, trajectory)``.


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp_and_right_jacobian(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(exp([theta]), J_r(theta)): for R(t) = R0 exp([theta(t)]) the body rate is J_r theta'."""
    angle = math.sqrt(float(theta @ theta))
    k = _skew(theta)
    k2 = k @ k
    if angle < 1e-6:
        return np.eye(3) + k + 0.5 * k2, np.eye(3) - 0.5 * k + k2 / 6.0
    s, c = math.sin(angle), math.cos(angle)
    exp = np.eye(3) + (s / angle) * k + ((1.0 - c) / angle**2) * k2
    jacobian = np.eye(3) - ((1.0 - c) / angle**2) * k + ((angle - s) / angle**3) * k2
    return exp, jacobian


def _saturated(u: np.ndarray, du: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """``u`` squashed radially into the open ball of radius ``limit`` (``limit tanh(|u| /
    limit)`` along ``u``: the identity near zero, smooth everywhere) and its time derivative."""
    r = math.sqrt(float(u @ u))
    if r < 1e-12:
        return u.copy(), du.copy()
    n = u / r
    squash = math.tanh(r / limit)
    radius = limit * squash
    along = float(n @ du)
    return radius * n, (1.0 - squash * squash) * along * n + (radius / r) * (du - along * n)


class _Sinusoids:
    """Per component, a seeded sum of sinusoids: ``sum a sin(w t + phi)`` and its derivatives."""

    def __init__(self, rng: np.random.Generator, components: int, terms: int,
                 amplitude: tuple[float, float], hz: tuple[float, float]) -> None:
        self.amp = rng.uniform(*amplitude, size=(components, terms))
        self.freq = rng.uniform(*hz, size=(components, terms)) * 2.0 * math.pi
        self.phase = rng.uniform(0.0, 2.0 * math.pi, size=(components, terms))

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(value, first derivative, second derivative) at ``t``, each (components,)."""
        angle = self.freq * t + self.phase
        sin, cos = np.sin(angle), np.cos(angle)
        return (np.sum(self.amp * sin, axis=1), np.sum(self.amp * self.freq * cos, axis=1),
                -np.sum(self.amp * self.freq**2 * sin, axis=1))


class _AnalyticTrajectory(Trajectory):
    """A trajectory whose ``state`` is exact at any time: ``rotations`` reads it."""

    def rotations(self, times: np.ndarray) -> Rotation:
        times = _checked_times(times)
        if len(times) == 0:
            return Rotation.from_quat(np.empty((0, 4)))
        return Rotation.from_matrix(np.array([self.state(t).rotation for t in times.tolist()]))

    def orientation(self, t: float) -> np.ndarray:
        return self.state(t).rotation


class WristTrajectory(_AnalyticTrajectory):
    """A hand turning the board at the wrist: a partial sphere about a base pose.

    The orientation is ``base @ exp([theta(t)])``: ``base`` a seeded uniformly random pose and
    ``theta`` three sums of three sinusoids (0.05-0.3 Hz) squashed smoothly into a ball of
    ``cone_deg`` (90 by default), so the board never turns more than ``cone_deg`` from its base
    pose and the earth's field, seen from the board, never enters the hemisphere opposite its
    direction in the base pose. Rates are a hand's: about 1 rad/s on average, peaks of 2-3.
    The hand also carries the board a few centimetres (three sinusoids per axis, 0.2-1 Hz, as
    ``tumble``); ``position(t)`` is that displacement, its second derivative the acceleration.
    """

    kind = 'wrist'

    def __init__(self, seed: int = 0, cone_deg: float = 90.0) -> None:
        if not (math.isfinite(cone_deg) and 0.0 < cone_deg <= 180.0):
            raise ValueError(f'cone_deg must be in (0, 180], got {cone_deg!r}')
        rng = np.random.default_rng([seed, 20])
        self.cone = math.radians(cone_deg)
        self.base = Rotation.random(random_state=rng).as_matrix()
        self._turn = _Sinusoids(rng, 3, 3, (0.4, 0.8), (0.05, 0.3))
        self._shake = _Sinusoids(np.random.default_rng([seed, 21]), 3, 3, (0.01, 0.03),
                                 (0.2, 1.0))

    def angle_from_base(self, t: float) -> float:
        """How far (rad) the board has turned from its base pose at ``t``."""
        u, du, _ = self._turn.at(_checked_time(t))
        return float(np.linalg.norm(_saturated(u, du, self.cone)[0]))

    def position(self, t: float) -> np.ndarray:
        """World-frame displacement (3,) in metres of the hand at ``t``."""
        return self._shake.at(_checked_time(t))[0]

    def state(self, t: float) -> MotionState:
        t = _checked_time(t)
        u, du, _ = self._turn.at(t)
        theta, dtheta = _saturated(u, du, self.cone)
        exp, jacobian = _exp_and_right_jacobian(theta)
        return MotionState(self.base @ exp, jacobian @ dtheta, self._shake.at(t)[2])


class DroneTrajectory(_AnalyticTrajectory):
    """A multirotor flying about: tilts of at most ``max_tilt_deg`` (30) and turns in yaw.

    The orientation is ``Rz(yaw) @ exp([a, b, 0])``: the yaw turns at a seeded 0.2-0.5 rad/s,
    sped up, slowed and at times reversed by two slow sinusoids; the tilt vector ``(a, b)``
    (rad, about horizontal axes of the yawed frame; its length is the angle between the body z
    axis and up) is two sums of three sinusoids (0.1-0.5 Hz) squashed smoothly into a disc of
    ``max_tilt_deg``.

    ``thrust`` (default): the drone holds its altitude, so its thrust along body z carries its
    weight and its tilt accelerates it sideways (``g tan(tilt)``, drag ignored): the
    accelerometer reads ``g / cos(tilt)`` along body z only, gravity's direction hidden while it
    tilts, as on a real multirotor. ``thrust=False``: the attitude alone, no linear acceleration
    (a board on a gimbal test stand), the accelerometer reading gravity.
    """

    kind = 'drone'

    def __init__(self, seed: int = 0, max_tilt_deg: float = 30.0, thrust: bool = True) -> None:
        if not (math.isfinite(max_tilt_deg) and 0.0 < max_tilt_deg < 90.0):
            raise ValueError(f'max_tilt_deg must be in (0, 90), got {max_tilt_deg!r}')
        rng = np.random.default_rng([seed, 22])
        self.max_tilt = math.radians(max_tilt_deg)
        self.thrust = bool(thrust)
        self._yaw0 = rng.uniform(-math.pi, math.pi)
        self._yaw_rate = rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.5)
        self._yaw_mod = _Sinusoids(rng, 1, 2, (0.8, 2.0), (0.02, 0.08))
        self._tilt = _Sinusoids(rng, 2, 3, (0.12, 0.3), (0.1, 0.5))

    def yaw(self, t: float) -> float:
        """The heading (rad, unwrapped) at ``t``: the yaw of the body x axis about world up."""
        return self._yaw0 + self._yaw_rate * t + float(self._yaw_mod.at(_checked_time(t))[0][0])

    def state(self, t: float) -> MotionState:
        t = _checked_time(t)
        mod, dmod, _ = self._yaw_mod.at(t)
        yaw = self._yaw0 + self._yaw_rate * t + float(mod[0])
        yaw_rate = self._yaw_rate + float(dmod[0])
        u, du, _ = self._tilt.at(t)
        tilt, dtilt = _saturated(u, du, self.max_tilt)
        theta, dtheta = np.array([tilt[0], tilt[1], 0.0]), np.array([dtilt[0], dtilt[1], 0.0])
        exp, jacobian = _exp_and_right_jacobian(theta)
        cy, sy = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]]) @ exp
        omega = exp.T @ np.array([0.0, 0.0, yaw_rate]) + jacobian @ dtheta
        acceleration = ZERO3
        if self.thrust:  # body z carries the weight: sideways g tan(tilt)
            up = rotation[:, 2]
            g = 9.80665
            acceleration = np.array([up[0] * g / up[2], up[1] * g / up[2], 0.0])
        return MotionState(rotation, omega, acceleration)


class CarriedTrajectory(Trajectory):
    """Another trajectory's turning, carried along a path of waypoints (a robot or a person
    walking through a room, for a world-fixed disturbance to be passed through).

    ``waypoints``: ``(time s, (x, y, z) m)`` in increasing time; between two the position moves
    with a minimum-jerk profile (at rest at each waypoint; the same position twice: a stop), and
    holds the first before it and the last after. ``position(t)`` is the path's position plus
    the carried trajectory's own (a hand's few centimetres), the linear acceleration theirs
    summed; orientation and body rate are the carried trajectory's.
    """

    kind = 'carried'

    def __init__(self, turning: Trajectory,
                 waypoints: tuple[tuple[float, tuple[float, float, float]], ...]) -> None:
        times = [float(w[0]) for w in waypoints]
        if not times or any(not math.isfinite(v) for v in times) or any(
                b <= a for a, b in zip(times[:-1], times[1:], strict=True)):
            raise ValueError('waypoints need at least one, at finite increasing times')
        self.turning = turning
        self._times = times
        self._points = [np.asarray(w[1], dtype=float).reshape(3) for w in waypoints]

    def _path(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, acceleration) of the path alone at ``t``."""
        index = bisect_right(self._times, t) - 1
        if index < 0:
            return self._points[0].copy(), ZERO3
        if index >= len(self._times) - 1:
            return self._points[-1].copy(), ZERO3
        start, end = self._times[index], self._times[index + 1]
        span = end - start
        s, _, dds = PosesTrajectory._profile((t - start) / span)
        step = self._points[index + 1] - self._points[index]
        return self._points[index] + s * step, step * (dds / span**2)

    def position(self, t: float) -> np.ndarray:
        """World-frame position (3,) in metres at ``t``."""
        t = _checked_time(t)
        own = getattr(self.turning, 'position', None)
        return self._path(t)[0] + (own(t) if callable(own) else ZERO3)

    def rotations(self, times: np.ndarray) -> Rotation:
        return self.turning.rotations(times)

    def orientation(self, t: float) -> np.ndarray:
        return self.turning.orientation(t)

    def state(self, t: float) -> MotionState:
        t = _checked_time(t)
        inner = self.turning.state(t)
        return MotionState(inner.rotation, inner.angular_velocity,
                           inner.linear_acceleration + self._path(t)[1])
