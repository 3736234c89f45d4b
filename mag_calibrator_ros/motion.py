"""Orientation trajectories and the earth's field for the simulated sensor, demo and benchmarks.

A magnetometer calibration is only as good as the orientations it saw, so the simulator moves the
sensor the way people and robots do: a hand tumbling the board (``tumble``), a ground robot
turning in place with a little tilt (``yaw``), or a board lying on the bench (``still``). Every
trajectory is deterministic for a seed so tests and benchmarks are repeatable.

Conventions: world frame ENU (x east, y north, z up); ``orientation(t)`` is the rotation matrix
world<-body, so a world vector ``v`` reads ``R.T @ v`` in the body frame.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation
else:

    class _LazyRotation:
        """scipy's Rotation, imported on first use: scipy.spatial costs 0.5 s, and a node that
        never simulates (a driver on real hardware) never needs it."""

        def __getattr__(self, name: str) -> object:
            from scipy.spatial.transform import Rotation

            return getattr(Rotation, name)

    Rotation = _LazyRotation()

TRAJECTORY_KINDS = ('tumble', 'yaw', 'still')


def earth_field(strength: float, inclination_deg: float) -> np.ndarray:
    """World-frame (ENU) earth field: ``F cos I`` towards north, ``F sin I`` downwards.

    Positive inclination dips the field below the horizon (northern hemisphere), so the up
    component is ``-F sin I``. Units are those of ``strength``.
    """
    strength = float(strength)
    inclination_deg = float(inclination_deg)
    if not math.isfinite(strength) or strength < 0.0:
        raise ValueError(f'field strength must be finite and >= 0, got {strength}')
    if not math.isfinite(inclination_deg) or abs(inclination_deg) > 90.0:
        raise ValueError(f'inclination must be within [-90, 90] degrees, got {inclination_deg}')
    inclination = math.radians(inclination_deg)
    return np.array([0.0, strength * math.cos(inclination), -strength * math.sin(inclination)])


class Trajectory:
    """A body orientation as a function of time (seconds, t >= 0)."""

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

    def rotations(self, times: np.ndarray) -> Rotation:
        times = _checked_times(times)
        return Rotation.from_quat(np.tile(self._quat, (len(times), 1)))


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


class TumbleTrajectory(Trajectory):
    """A hand tumbling the board: body angular velocity is low-pass filtered white noise.

    Each body axis's rate is white noise through two cascaded first-order low-passes (time constant
    ``correlation_s``), scaled to ``rate_std`` rad/s per axis; peaks reach several rad/s, and the
    random walk on SO(3) visits every orientation within 30-60 s. The rate is integrated exactly
    on a 25 Hz knot grid (piecewise-constant rate between knots), extended lazily and forgotten
    after ``retain_s`` seconds so a long-running simulator stays bounded in memory.
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


def make_trajectory(kind: str, seed: int = 0) -> Trajectory:
    """The trajectory named ``kind`` ('tumble' | 'yaw' | 'still'), deterministic for ``seed``."""
    factories = {'tumble': TumbleTrajectory, 'yaw': YawTrajectory, 'still': StillTrajectory}
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
