# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Magnetometer readings paired with the accelerometer sample taken with them.

The IMU's samples (``CalibrationSession.process_imu``) wait in a short ring; each accepted
magnetometer reading takes the one nearest its stamp. IMU messages come on another topic through
another DDS reader, so a busy computer can deliver them after the magnetometer readings of their
instant: a reading's pair is decided only once an IMU sample at or after its stamp has arrived,
or a bound has passed (``settle``). Both are counted in message stamps and arrival order, so a
recording replayed offline decides the same; only what the reading teaches waits, not its
correction. A pair tells the alignment which way is
up while the sensor is held still (``alignment.StaticAttitudes``) and the buffer the gravity
direction behind a sample (``levelled.py``): the one ``gravity.GravityTracker`` holds, and none
while the specific force is the robot accelerating.

Only what can mean that is paired: a sample that is no plausible specific force, or that is in
another frame than the magnetometer's (an alignment between two frames would rotate the
corrected field out of the frame its header names), is refused and counted by reason. When an
IMU is there but its stamps never meet the readings' (another clock, a delay), most readings
go unpaired: that is measured and said, with the offset, and, live, which it is: the times DDS
gives each message (``Delivery``) tell a stream this node handles late, or one delivered late,
from stamps on another clock. So is a gyroscope whose rates do not turn gravity's direction as
the accelerometer sees it turn (``gravity.RateCheck``: deg/s).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
import math
import statistics
import sys
from typing import NamedTuple

from mag_calibrator_ros.calibration.live.gravity import GravityTracker

Vector = tuple[float, float, float]
Pair = tuple[Vector, Vector | None, Vector | None]
"""(specific force, angular rate or None, gravity's direction or None) of the accelerometer
sample paired with a reading; gravity's is None while the robot accelerated
(``GravityTracker``)."""

IMU_RING = 256
"""Recent accelerometer samples kept to pair magnetometer readings with (256 ms at 1 kHz)."""
PAIR_TOLERANCE_NS = 20_000_000
"""A magnetometer reading pairs with the accelerometer sample nearest its stamp within 20 ms
(a 50 Hz IMU); a still reading does not change in that time, a moving one is never still."""

IMU_REASONS = ('non_finite', 'too_weak', 'too_strong', 'other_frame')
"""Why an accelerometer sample is not kept: a NaN/Inf (or no three numbers); a specific force
below or beyond ``force_range``; a frame other than the magnetometer stream's."""

SPECIFIC_FORCE_RANGE = (1.0, 500.0)
"""Plausible |specific force| in m/s^2 (sensor_msgs/Imu, REP-103). At rest an accelerometer
reads g (9.81 m/s^2); a moving robot or a hand adds a few m/s^2, a shock tens. Below 1 m/s^2
(a tenth of g: free fall, a zero or underflowing value, or another unit such as g) a sample
tells nothing of gravity's direction; beyond 500 m/s^2 (about 50 g: the ICM-20948's largest
full scale, 16 g on every axis at once, is 27.7 g) it is no reading of a moving robot."""

STARVATION_WINDOW = 200
"""Readings over which pairing is judged while an IMU is there (2 s at 100 Hz). Starvation is
said when more than three in four of them found no sample (stamps on other clocks leave nearly
all unpaired; IMU messages that a busy computer delivers after the readings of their instant,
some), and over once fewer than half did."""
STARVATION_MIN = 50
"""Readings judged before starvation is said (one unpaired reading is no pattern)."""
IMU_ABSENT_READINGS = 25
"""Readings without a new accelerometer sample after which the IMU counts as gone, not late
(its stream stopped: nothing to pair with, nothing to say about its stamps). Half of
STARVATION_MIN, so the readings after an IMU stops never make half a window unpaired alone."""
PAIR_WAIT_NS = 500_000_000
"""The longest a reading waits for the IMU sample after its stamp, in stream time: readings
are decided unpaired once a reading 0.5 s newer has arrived. Longer than an IMU topic lags
behind the magnetometer's on a loaded computer (a queue of sensor-data depth at 225 Hz is
0.44 s); short next to the seconds a fit waits for its samples."""
PAIR_WAIT_READINGS = 1024
"""The most readings waiting for their IMU sample (a memory bound when stamps stand still)."""
FRAME_WARNING_MESSAGES = IMU_RING
"""A frame refusal is shown in /diagnostics until this many IMU messages passed without one."""
MAX_WARNED_FRAMES = 16
"""Frame pairs warned about once each (a bound: a frame name per message cannot fill memory)."""


class Delivery(NamedTuple):
    """When one message was sent (the publisher's clock), received by this process's DDS reader
    and handled by its callback (this computer's clock), in ns: rclpy's MessageInfo and
    ``time.time_ns()``. A replay has none."""

    sent_ns: int
    received_ns: int
    handled_ns: int


@dataclass
class DeliveryLags:
    """How late one stream's recent messages were handled: after being sent (transport and this
    node's queue) and after arriving (this node's queue alone), medians in seconds."""

    _lags: deque[tuple[int, int]] = field(
        default_factory=lambda: deque(maxlen=STARVATION_WINDOW))

    def add(self, delivery: Delivery | None) -> None:
        if delivery is not None and delivery.sent_ns > 0 and delivery.received_ns > 0:
            self._lags.append((delivery.handled_ns - delivery.sent_ns,
                               delivery.handled_ns - delivery.received_ns))

    def after_sent(self) -> float | None:
        return statistics.median(lag for lag, _ in self._lags) / 1e9 if self._lags else None

    def queued(self) -> float | None:
        return statistics.median(wait for _, wait in self._lags) / 1e9 if self._lags else None


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


def _vector(values: Sequence[float] | None) -> Vector | None:
    """Three finite floats, or None."""
    try:
        x, y, z = (float(value) for value in values)
    except (TypeError, ValueError):
        return None
    return (x, y, z) if math.isfinite(x) and math.isfinite(y) and math.isfinite(z) else None


def force_problem(force: Vector, force_range: tuple[float, float] | None) -> str | None:
    """Why a finite specific force is unusable ('too_weak', 'too_strong'), or None. The norm is
    ``math.hypot``'s, which neither underflows nor overflows on the way: (1e-200, 0, 0) is
    1e-200, not 0. Without a range (the unit unknown) only a norm that is zero, subnormal or
    beyond the largest float is refused, so gravity's direction can always be computed."""
    norm = math.hypot(*force)
    low, high = force_range if force_range is not None else (sys.float_info.min, math.inf)
    if not norm >= max(low, sys.float_info.min):
        return 'too_weak'
    if not norm <= high or math.isinf(norm):
        return 'too_strong'
    return None


class ImuPairing:
    """The accelerometer ring, its refusals by reason and the pairing's health, for
    /diagnostics and the log."""

    def __init__(self, force_range: tuple[float, float] | None = SPECIFIC_FORCE_RANGE,
                 gravity: GravityTracker | None = None) -> None:
        self.force_range = force_range
        """Plausible |specific force| (SPECIFIC_FORCE_RANGE, m/s^2); None when the unit is
        unknown (``mag_calibrator_fit`` reads logs in counts or g)."""
        self._ring: deque[tuple[int, float, float, float, Vector | None, str, Vector | None]
                          ] = deque(maxlen=IMU_RING)
        self.gravity = gravity if gravity is not None else GravityTracker()
        """Gravity's direction from the samples kept, and how many measured none (a benchmark
        gives another tracker to compare with)."""
        self.rate = RateMeter()
        self.accepted = 0
        self.refusals = dict.fromkeys(IMU_REASONS, 0)
        self.paired = 0
        """Magnetometer readings paired with an accelerometer sample."""
        self.other_frame: tuple[str, str] | None = None
        """(IMU frame, magnetometer frame) of the latest sample refused for its frame."""
        self._since_other_frame = FRAME_WARNING_MESSAGES
        self._warned_frames: set[tuple[str, str]] = set()
        self._gaps: deque[int] = deque(maxlen=STARVATION_WINDOW)  # nearest sample - reading, ns
        self._unpaired = 0  # readings in _gaps that found no sample within the tolerance
        self._since_sample = IMU_ABSENT_READINGS  # readings since the latest kept sample
        self._starving = False
        self._warnings: list[str] = []
        self._rates_said = False  # the gyroscope's disagreement is logged once (until clear)
        # (stamp, frame, item, the latest sample's stamp when the reading arrived)
        self._waiting: deque[tuple[int, str | None, object, int | None]] = deque()
        self._decided: list[tuple[object, Pair | None]] = []
        self._latest_sample: int | None = None  # the stamp of the latest kept sample
        self._readings_since_sample = IMU_ABSENT_READINGS
        self.imu_lags, self.mag_lags = DeliveryLags(), DeliveryLags()
        """How late this node handled the latest IMU messages and readings (live only)."""

    @property
    def refused(self) -> int:
        """Accelerometer samples refused, every reason."""
        return sum(self.refusals.values())

    def add(self, stamp_ns: int, accel: Sequence[float], gyro: Sequence[float] | None = None,
            frame_id: str = '', stream_frame: str | None = None,
            delivery: Delivery | None = None) -> bool:
        """Keep one accelerometer (and gyroscope, rad/s) sample; O(1). False when refused (by
        IMU_REASONS): a non-finite or implausible specific force, or a ``frame_id`` other than
        the magnetometer stream's ``stream_frame`` (None while unknown: then readings pair only
        with samples of their own frame). A gyroscope sample with a non-finite value counts as
        none."""
        self.rate.count += 1
        self.imu_lags.add(delivery)
        self._since_other_frame += 1
        force = _vector(accel)
        reason = 'non_finite' if force is None else force_problem(force, self.force_range)
        frame_id = str(frame_id)
        if reason is None and stream_frame is not None and frame_id != stream_frame:
            reason = 'other_frame'
            self._refuse_frame(frame_id, stream_frame)
        if reason is not None:
            self.refusals[reason] += 1
            return False
        rate = None if gyro is None else _vector(gyro)
        up = self.gravity.update(int(stamp_ns), force, rate, frame_id)
        if not (self._rates_said or self.gravity.rates.agree):
            self._rates_said = True
            self._warnings.append(self.rates_problem())
        self._ring.append((int(stamp_ns), *force, rate, frame_id, up))
        self.accepted += 1
        self._since_sample = self._readings_since_sample = 0
        self._latest_sample = int(stamp_ns)
        waiting = self._waiting
        while waiting and waiting[0][0] <= stamp_ns:  # decided while the samples are in the ring
            self._decide()
        return True

    def settle(self, stamp_ns: int, frame_id: str | None, item: object,
               delivery: Delivery | None = None) -> list[tuple[object, Pair | None]]:
        """Take one reading (``item``: whatever the caller learns from) and give back, in
        arrival order, the readings whose pair is now decided, each with its pair or None.

        A reading waits while an IMU is there and no sample at or after its stamp has arrived
        yet; it is decided once one does (then no later one can be nearer), once a reading
        PAIR_WAIT_NS newer arrives, or beyond PAIR_WAIT_READINGS. Without an IMU (none kept, or
        none for IMU_ABSENT_READINGS readings) nothing waits; a stamp going back (a new clock)
        decides every waiting reading first."""
        self.mag_lags.add(delivery)
        waiting = self._waiting
        if waiting and stamp_ns < waiting[-1][0]:
            self._decide_all()
        waiting.append((int(stamp_ns), frame_id, item, self._latest_sample))
        self._readings_since_sample += 1
        if (self._latest_sample is None or self._readings_since_sample > IMU_ABSENT_READINGS):
            self._decide_all()
        else:
            while waiting and (waiting[0][0] <= self._latest_sample
                               or waiting[0][0] + PAIR_WAIT_NS <= stamp_ns
                               or len(waiting) > PAIR_WAIT_READINGS):
                self._decide()
        decided, self._decided = self._decided, []
        return decided

    def flush(self) -> list[tuple[object, Pair | None]]:
        """Decide every waiting reading now, with the samples there are (a request fits every
        reading received before it), and give back every decided one, as ``settle``."""
        self._decide_all()
        decided, self._decided = self._decided, []
        return decided

    @property
    def waiting(self) -> int:
        """Readings whose pair is not decided yet."""
        return len(self._waiting)

    def _decide(self) -> None:
        stamp_ns, frame_id, item, latest = self._waiting.popleft()
        self._decided.append((item, self.pair(stamp_ns, frame_id, latest)))

    def _decide_all(self) -> None:
        while self._waiting:
            self._decide()

    def _refuse_frame(self, frame_id: str, stream_frame: str) -> None:
        self.other_frame, self._since_other_frame = (frame_id, stream_frame), 0
        if (frame_id, stream_frame) in self._warned_frames:
            return
        if len(self._warned_frames) < MAX_WARNED_FRAMES:
            self._warned_frames.add((frame_id, stream_frame))
            self._warnings.append(
                f"imu/data_raw is in frame '{frame_id}' but imu/mag in '{stream_frame}': its "
                'samples are not paired (aligning to an IMU in another frame would rotate the '
                "corrected field out of the frame its header names); publish the IMU in the "
                "magnetometer's frame (the driver's frame_id), or set use_imu false")

    def pair(self, stamp_ns: int, frame_id: str | None = None,
             arrival_ns: int | None = None) -> Pair | None:
        """Decide now (``settle`` decides when): the accelerometer sample of ``frame_id``
        (None: any) nearest ``stamp_ns`` within PAIR_TOLERANCE_NS, searched from the newest
        back (samples arrive in stamp order: a few steps). How near the nearest one was,
        paired or not, feeds the starvation measure; for a reading left unpaired with every
        sample older, how far behind the latest sample was when it arrived (``arrival_ns``:
        waiting moved newer samples in, not the clocks)."""
        best, best_gap = None, math.inf
        ring = self._ring
        if ring and ring[0][0] > stamp_ns and (frame_id is None or ring[0][5] == frame_id):
            best, best_gap = ring[0], ring[0][0] - stamp_ns  # every sample is newer
        else:
            for sample in reversed(ring):
                if frame_id is not None and sample[5] != frame_id:
                    continue
                gap = sample[0] - stamp_ns
                if abs(gap) < abs(best_gap):
                    best, best_gap = sample, gap
                elif gap < 0:
                    break  # older still: only further away
        if best is None or abs(best_gap) > PAIR_TOLERANCE_NS:
            late = best is not None and best_gap < 0 and arrival_ns is not None
            self._judge(min(best_gap, arrival_ns - stamp_ns) if late else best_gap)
            return None
        self._judge(best_gap)
        self.paired += 1
        return (best[1], best[2], best[3]), best[4], best[6]

    def _judge(self, gap: float) -> None:
        """One reading's nearest gap into the starvation window, while an IMU is there."""
        self._since_sample += 1
        if self._since_sample > IMU_ABSENT_READINGS or math.isinf(gap):
            if self._gaps:
                self._gaps.clear()
                self._unpaired, self._starving = 0, False
            return
        gaps = self._gaps
        if len(gaps) == gaps.maxlen and abs(gaps[0]) > PAIR_TOLERANCE_NS:
            self._unpaired -= 1
        gaps.append(int(gap))
        if abs(gap) > PAIR_TOLERANCE_NS:
            self._unpaired += 1
        if len(gaps) < STARVATION_MIN:
            return
        if not self._starving and 4 * self._unpaired > 3 * len(gaps):
            self._starving = True
            self._warnings.append(self.starvation())
        elif self._starving and 2 * self._unpaired < len(gaps):
            self._starving = False  # mostly paired again: a later starvation is said anew

    def starvation(self) -> str:
        """Why most readings find no accelerometer sample to pair with ('' when they do)."""
        if not self._starving:
            return ''
        gaps = list(self._gaps)
        offset = statistics.median(gaps) / 1e9
        what = (f'{self._unpaired} of the last {len(gaps)} imu/mag readings found no '
                f'imu/data_raw sample within {PAIR_TOLERANCE_NS / 1e6:.0f} ms, so they are not '
                'paired (no alignment to the IMU, no levelling)')
        if abs(offset) * 1e9 > PAIR_TOLERANCE_NS:
            return self._offset_cause(offset, what)
        spacing = statistics.median(abs(gap) for gap in gaps) / 1e6
        return (f'imu/data_raw samples are too sparse: {what} (median distance to the nearest '
                f'{spacing:.0f} ms); publish the IMU at 50 Hz or more')

    def _offset_cause(self, offset: float, what: str) -> str:
        """Stamps ``offset`` s apart (IMU minus magnetometer, at arrival), said with its cause
        when the times DDS gave the messages tell it: one stream handled later than the other
        by at least half the offset, the other way round, is delivery (this node's own queue
        when that is where the messages waited), not clocks."""
        side = 'behind' if offset < 0 else 'ahead of'
        stamps = f"imu/data_raw stamps are {abs(offset):.3f} s {side} imu/mag's"
        imu, mag = self.imu_lags.after_sent(), self.mag_lags.after_sent()
        if imu is None or mag is None:  # a replay, or a middleware without the times
            return (f'{stamps}: {what}; stamp both from one clock (the same driver, or '
                    'synchronised clocks), and deliver imu/data_raw without delay')
        skew = imu - mag  # > 0: the IMU's messages reach the callback later
        if skew * offset < 0 and abs(skew) >= abs(offset) / 2:
            late, other = (('imu/data_raw', 'imu/mag') if skew > 0
                           else ('imu/mag', 'imu/data_raw'))
            queued = (self.imu_lags if skew > 0 else self.mag_lags).queued()
            slow, quick = max(imu, mag), min(imu, mag)
            if queued >= slow / 2:
                return (f'{stamps}, because this node is behind: it handles {late} '
                        f'{queued:.3f} s after it arrives ({other} {quick:.3f} s after '
                        f'it was sent), not because of the clocks: {what}; give the calibrator '
                        f'more CPU (fewer jobs beside it), or publish {late} at a lower rate')
            return (f'{stamps}, because {late} reaches this node {slow:.3f} s after it was sent '
                    f'({other} {quick:.3f} s), not because of the clocks: {what}; publish both '
                    'from a computer with time to spare, or over a faster link')
        return (f'{stamps} although this node handles both within {max(imu, mag):.3f} s of '
                f'their sending: their stamps come from different clocks: {what}; stamp both '
                'from one clock (the same driver, or synchronised clocks)')

    def rates_problem(self) -> str:
        """Why the gyroscope's rates disagree with the accelerometer ('' when they do not)."""
        problem = self.gravity.rates.problem()
        return f'imu/data_raw angular_velocity: {problem}' if problem else ''

    def warning(self) -> str:
        """What is wrong with the IMU input now, for a /diagnostics WARN ('' if nothing)."""
        if self._since_other_frame < FRAME_WARNING_MESSAGES and self.other_frame is not None:
            imu, mag = self.other_frame
            return (f"imu/data_raw samples in frame '{imu}' are refused: imu/mag is in "
                    f"'{mag}' (publish the IMU in the magnetometer's frame)")
        return self.starvation() or self.rates_problem()

    def take_warnings(self) -> list[str]:
        """New warnings since the last call, each said once (a frame pair, a starvation; the
        gyroscope's rates disagreeing, once until ``clear``: a verdict near its bound may come
        and go, /diagnostics shows it as it is)."""
        warnings, self._warnings = self._warnings, []
        return warnings

    @property
    def has_warnings(self) -> bool:
        return bool(self._warnings)

    def clear(self) -> None:
        """Forget the samples and the readings waiting for one (a reset: a new sensor may
        follow; the session drops what it held too); the counters stay."""
        self._ring.clear()
        self.gravity.restart()
        self._waiting.clear()
        self._decided.clear()
        self._latest_sample, self._readings_since_sample = None, IMU_ABSENT_READINGS
        self._gaps.clear()
        self._unpaired, self._starving = 0, False
        self._since_sample = IMU_ABSENT_READINGS
        self._rates_said = False


__all__ = [
    'IMU_REASONS',
    'IMU_RING',
    'Delivery',
    'PAIR_TOLERANCE_NS',
    'PAIR_WAIT_NS',
    'PAIR_WAIT_READINGS',
    'SPECIFIC_FORCE_RANGE',
    'ImuPairing',
    'Pair',
    'RateMeter',
    'force_problem',
]
