"""Magnetometer readings paired with the accelerometer sample taken with them.

The IMU's samples (``CalibrationSession.process_imu``) wait in a short ring; each accepted
magnetometer reading takes the one nearest its stamp. A pair tells the alignment which way is
up while the sensor is held still (``alignment.StaticAttitudes``) and the buffer the gravity
direction behind a sample (``levelled.py``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
import math

Vector = tuple[float, float, float]
Pair = tuple[Vector, Vector | None]
"""(specific force, angular rate or None) of the accelerometer sample paired with a reading."""

IMU_RING = 256
"""Recent accelerometer samples kept to pair magnetometer readings with (256 ms at 1 kHz)."""
PAIR_TOLERANCE_NS = 20_000_000
"""A magnetometer reading pairs with the accelerometer sample nearest its stamp within 20 ms
(a 50 Hz IMU); a still reading does not change in that time, a moving one is never still."""


@dataclass
class RateMeter:
    """Messages per second since the previous reading (called at the diagnostics rate)."""

    count: int = 0
    _last_count: int = 0
    _last_time: float | None = None
    rate: float = 0.0

    def read(self, now: float) -> float:
        if self._last_time is not None and now > self._last_time:
            self.rate = (self.count - self._last_count) / (now - self._last_time)
        self._last_count, self._last_time = self.count, now
        return self.rate


class ImuPairing:
    """The accelerometer ring and its counters, for /diagnostics."""

    def __init__(self) -> None:
        self._ring: deque[tuple[int, float, float, float, Vector | None]] = deque(
            maxlen=IMU_RING)
        self.rate = RateMeter()
        self.accepted = 0
        self.refused = 0
        self.paired = 0
        """Magnetometer readings paired with an accelerometer sample."""

    def add(self, stamp_ns: int, accel: Sequence[float],
            gyro: Sequence[float] | None = None) -> bool:
        """Keep one accelerometer (and gyroscope, rad/s) sample; O(1). False when refused
        (non-finite or zero specific force). A gyroscope sample with a non-finite value counts
        as none."""
        self.rate.count += 1
        try:
            ax, ay, az = (float(value) for value in accel)
        except (TypeError, ValueError):
            ax = ay = az = math.nan
        if not (math.isfinite(ax + ay + az) and (ax or ay or az)):
            self.refused += 1
            return False
        rates = None
        if gyro is not None:
            try:
                gx, gy, gz = (float(value) for value in gyro)
            except (TypeError, ValueError):
                gx = gy = gz = math.nan
            rates = (gx, gy, gz) if math.isfinite(gx + gy + gz) else None
        self._ring.append((int(stamp_ns), ax, ay, az, rates))
        self.accepted += 1
        return True

    def pair(self, stamp_ns: int) -> Pair | None:
        """The accelerometer sample nearest ``stamp_ns`` within PAIR_TOLERANCE_NS, searched from
        the newest back (samples arrive in stamp order: a few steps)."""
        if not self._ring:
            return None
        best, best_gap = None, PAIR_TOLERANCE_NS + 1
        for sample in reversed(self._ring):
            gap = sample[0] - stamp_ns
            if abs(gap) < best_gap:
                best, best_gap = sample, abs(gap)
            elif gap < 0:
                break  # older still: only further away
        if best is None:
            return None
        self.paired += 1
        return (best[1], best[2], best[3]), best[4]

    def clear(self) -> None:
        """Forget the samples (a reset: a new sensor may follow); the counters stay."""
        self._ring.clear()


def up_direction(accel: Sequence[float]) -> Vector:
    """Gravity's unit direction from a paired specific force (never zero: ``add`` refuses
    that)."""
    ax, ay, az = accel
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    return ax / norm, ay / norm, az / norm


__all__ = ['IMU_RING', 'PAIR_TOLERANCE_NS', 'ImuPairing', 'Pair', 'RateMeter', 'up_direction']
