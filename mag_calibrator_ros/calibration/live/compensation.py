# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field between messages: inputs paired with readings, kept for the worker.

``CompensationLearner`` is the live side of ``fit/compensation.py``. Per reading it does O(k)
work: pairs the reading with the temperature (``imu/temperature``, nearest stamp) and the k
interference inputs (``interference_inputs``: a current, a speed), removes the compensation in
force (``K u + c (T - T0)``) so everything after it (buffer, evidence, fits) sees the Earth's
field and the static iron only, and keeps the raw reading with its inputs, decimated, for the
next compensation fit. The fit itself runs in the fit worker (a ``compensate`` FitJob); whether
it goes in force is ``verdicts.compensation_verdict``: only on held-out readings it improves,
and only with terms the inputs' variation determined. Readings screening refused never reach it.

The inputs are named by parameter (``live/inputs.py``). With an IMU, each kept reading also
carries the attitude integrated from the gyroscope (O(1) per IMU sample), so the fit can compare
readings between which the robot barely turned (``fit/compensation.py`` gyro_pairs).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration, Compensation
from mag_calibrator_ros.calibration.fit.compensation import (
    LEARNED,
    MIN_READINGS,
    TEMPERATURE,
    CompensationData,
    interference_grade,
)
from mag_calibrator_ros.calibration.fit.input_sanity import TEMPERATURE_RANGE_C
from mag_calibrator_ros.calibration.live.inputs import InputSpec, parse_input
from mag_calibrator_ros.calibration.live.jobs import (
    REFERENCE_OPTIONS,
    FitJob,
    JobOutcome,
    kept_compensation,
)
from mag_calibrator_ros.calibration.live.report import CalibrationAttempt
from mag_calibrator_ros.calibration.live.verdicts import Verdict, compensation_verdict

SAMPLE_RING = 32
"""Recent samples of each input and of the temperature, to pair readings with by stamp."""
MAX_TEMPERATURE_STEP_C = 5.0
MAX_TEMPERATURE_RATE_C_S = 1.0
"""A temperature step beyond MAX_TEMPERATURE_STEP_C at more than this rate is none a board
makes (``temperature``)..."""
CONFIRM_SAMPLES = 3
"""...unless this many samples in a row agree on the new level."""
SILENT_INTERVALS = 10
SILENT_MIN_S = 2.0
"""An input is silent after SILENT_INTERVALS of its own sample intervals without one (at least
SILENT_MIN_S of stream): its own field is then held at its last value, which a publisher that
sends only on change (cmd_vel) means, and a driver that stopped does not (``silence_note``)."""
INPUT_TOLERANCE_NS = 500_000_000
"""A reading learns only from input samples within 0.5 s of its stamp (fresh); the correction
uses the latest value whatever its age (an input that stopped changing still holds)."""
TEMPERATURE_TOLERANCE_NS = 2_000_000_000
"""The driver publishes the die temperature at up to 10 Hz; it changes slowly."""
KEEP_EVERY_S = 0.05
"""Stream seconds between kept readings (20 per second: a fit's worth of variety, bounded)."""
KEPT = 4000
"""Readings kept to learn from (200 s at KEEP_EVERY_S), and HELD of them held out."""
HELD = 1000
ROW_INPUTS = 10
"""A kept row: stream seconds, the reading (3), degrees Celsius, the gyroscope's stretch and
attitude (5), then the inputs (from this column on)."""
HOLD_OUT_EVERY = 5
LEARN_PERIOD_S = 10.0
"""Stream seconds between compensation fits while there is something to learn."""
QUICK_PERIOD_S = 2.0
"""The same while ``~/learn_compensation`` waits for an answer (a person is waiting)."""
MAX_WINDOW_S = 600.0
"""The longest ``~/learn_compensation`` waits (``compensation_timeout``'s upper bound)."""
PENDING = 40
"""Readings waiting for their inputs' samples, at most (one every KEEP_EVERY_S: 2 s of stream);
the oldest is then paired with the sample nearest it within INPUT_TOLERANCE_NS, or dropped."""
GYRO_GAP_NS = 250_000_000
"""A longer gap between gyroscope samples (or a non-finite one) ends a stretch of integrated
attitude: the rotation across it is not known, so no readings across it are compared. A log's
10 Hz rows (ArduPilot's MAG rate) come 100 ms apart give or take a millisecond: a 100 ms limit
broke every fourth step of a real hover log, and no pair was made."""
NO_ATTITUDE = (math.nan,) * 5


def covered_terms(compensation: Compensation | None, own: Sequence[str]) -> np.ndarray:
    """(k + 1,) booleans: which of the ``own`` inputs, then the temperature, ``compensation``
    has a term for (a column of K not zero, matched as ``input_columns`` matches; c not zero
    with its T0)."""
    covered = np.zeros(len(own) + 1, dtype=bool)
    if compensation is None:
        return covered
    columns = input_columns(compensation.inputs, own)
    if columns is not None and len(columns) == len(compensation.inputs):
        for position, column in enumerate(columns):
            covered[column] |= bool(np.any(compensation.interference[:, position]))
    covered[-1] = (compensation.reference_temperature is not None
                   and bool(np.any(compensation.temperature_coefficient)))
    return covered


def input_columns(names: Sequence[str], own: Sequence[str]) -> list[int] | None:
    """Where each of a compensation's input ``names`` is among the ``own`` inputs here: by
    name when all are here, else by position when the counts agree (a file learnt offline
    names its columns, the node its topics); None when they cannot be matched."""
    names, own = tuple(names), tuple(own)
    if all(name in own for name in names):
        return [own.index(name) for name in names]
    if len(names) == len(own):
        return list(range(len(own)))
    return None


@dataclass
class _Window:
    """An open ``~/learn_compensation``: its ticket and its span in stream seconds."""

    ticket: int
    opened: float
    deadline: float
    units: str = 'T'
    learned: str = ''
    """What the latest compensation put in force in the window learned (the answer's text)."""
    learned_at: float = 0.0
    latest: str = ''
    """Why the latest fit in the window put nothing in force."""


class _Series:
    """Recent (stamp, value) samples of one input; nearest by stamp, O(ring) from the newest."""

    def __init__(self) -> None:
        self.samples: deque[tuple[int, float]] = deque(maxlen=SAMPLE_RING)
        self.latest = math.nan
        self.received = 0
        self.refused = 0  # samples no robot makes (``refuse``)

    def add(self, stamp_ns: int, value: float) -> None:
        if math.isfinite(value):
            self.samples.append((stamp_ns, value))
            self.latest = value
            self.received += 1

    def refuse(self, message: str) -> str | None:
        """Count a dropped sample; ``message`` the first time only (said once)."""
        self.refused += 1
        return message if self.refused == 1 else None

    def silent_for(self, stamp_ns: int) -> float | None:
        """Stream seconds since the last sample when it is silent (SILENT_INTERVALS), or None."""
        if len(self.samples) < 2:
            return None
        stamps = np.array([stamp for stamp, _ in self.samples], dtype=float)
        gap = (stamp_ns - stamps[-1]) / 1e9
        interval = float(np.median(np.diff(stamps))) / 1e9
        return gap if gap > max(SILENT_MIN_S, SILENT_INTERVALS * interval) else None

    def at(self, stamp_ns: int, tolerance_ns: int) -> float:
        """The value nearest ``stamp_ns`` within the tolerance, else NaN."""
        best, gap = math.nan, tolerance_ns + 1
        for stamp, value in reversed(self.samples):
            distance = abs(stamp - stamp_ns)
            if distance < gap:
                best, gap = value, distance
            elif stamp < stamp_ns:
                break
        return best if gap <= tolerance_ns else math.nan


class _Rows:
    """Rows of ``width`` floats in arrival order, the oldest dropped past ``limit``. A fit's
    copy is one contiguous copy on the message thread (a deque of tuples took about 10 ms
    for 5000 rows, measured on the 2-core machine; a person waits every QUICK_PERIOD_S)."""

    def __init__(self, limit: int, width: int) -> None:
        self._rows = np.empty((limit, width))
        self._next = self._count = 0

    def append(self, row: tuple[float, ...]) -> None:
        self._rows[self._next] = row
        self._next = (self._next + 1) % len(self._rows)
        self._count = min(self._count + 1, len(self._rows))

    def __len__(self) -> int:
        return self._count

    def clear(self) -> None:
        self._next = self._count = 0

    def copy(self) -> np.ndarray:
        """(n, width), oldest first."""
        if self._count < len(self._rows):
            return self._rows[:self._count].copy()
        return np.concatenate([self._rows[self._next:], self._rows[:self._next]])


def _without_drift(rows: np.ndarray, drift: tuple[float, float, float], t0: float
                   ) -> np.ndarray:
    """Kept rows with ``c (T - T0)`` taken from their reading (none where T is unknown)."""
    rows = rows.copy()
    rows[:, 1:4] -= np.outer(np.nan_to_num(rows[:, 4] - t0), drift)
    return rows


class CompensationLearner:
    """The inputs, the readings kept with them, and when the next compensation fit is due."""

    def __init__(self, inputs: tuple[str, ...] = (), use_temperature: bool = True,
                 learn: bool = True) -> None:
        self.specs: tuple[InputSpec, ...] = ()
        self.unmatched: tuple[str, ...] = ()  # a compensation's inputs this node lacks
        self.series: list[_Series] = []
        self.temperature_series = _Series()
        self.learn = learn
        self.use_temperature = use_temperature
        self._window: _Window | None = None  # an open ~/learn_compensation
        self.anchor: np.ndarray | None = None
        """The inputs and temperature where the calibration in force is right for raw readings
        (``carry``; NaN: unknown): fits hold the offset there (``_anchor_for_fits``), as a robot
        on a stand or driving straight shows the field one way only."""
        self.covered = np.zeros(1, dtype=bool)
        """Which of those terms the compensation in force has (held exactly there)."""
        self._from_file = False  # the calibration in force came from a file or parameters
        self._temperature_step = (math.nan, 0)  # a step's new level, and samples agreeing
        self.reset()
        self.configure(inputs, use_temperature, learn)
        self.last_fit = None
        """The latest CompensationFit (reports: what each term needs)."""

    def configure(self, inputs: tuple[str, ...], use_temperature: bool, learn: bool) -> None:
        """New inputs forget what was kept (its columns no longer match)."""
        specs = tuple(spec for spec in map(parse_input, inputs) if not isinstance(spec, str))
        if tuple(spec.text for spec in specs) != tuple(spec.text for spec in self.specs):
            self.specs = specs
            self.series = [_Series() for _ in specs]
            self.reset()
        self.use_temperature, self.learn = use_temperature, learn

    def name_inputs(self, names: tuple[str, ...]) -> None:
        """Inputs a recording names (``mag_calibrator_fit``: a log's current columns, a bag's
        BatteryState topics), fed by ``input`` as the node's subscriptions feed theirs; forgets
        what was kept, as a new list of inputs does."""
        self.specs = tuple(InputSpec(name, '', (), False, name) for name in names)
        self.series = [_Series() for _ in names]
        self.reset()

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(spec.text for spec in self.specs)

    def reset(self) -> None:
        """Forget the kept readings and the inputs' samples (``~/reset``)."""
        width = ROW_INPUTS + len(self.series)  # see _settle
        self._kept, self._held = _Rows(KEPT, width), _Rows(HELD, width)
        self._next_keep = -math.inf
        self._count = 0
        self._next_fit = 0.0
        self._last_stamp: int | None = None
        for series in (*self.series, self.temperature_series):
            series.samples.clear()
        self.last_fit = None
        self._pending: deque[tuple] = deque()
        self._stretch = getattr(self, '_stretch', 0) + 1
        self._attitude: list[float] | None = None  # quaternion (x, y, z, w), this stretch
        self._gyro_stamp: int | None = None
        self.restart_mean()

    def restart_mean(self) -> None:
        """The buffer was emptied: the mean inputs of its readings start again."""
        self._sums = [0.0] * (len(self.series) + 1)  # the inputs', then the temperature's
        self._counts = [0] * (len(self.series) + 1)

    # -- per message (O(k)) --------------------------------------------------------------------

    def temperature(self, stamp_ns: int | None, celsius: float) -> str | None:
        """One ``sensor_msgs/Temperature`` sample (degrees Celsius). One outside
        TEMPERATURE_RANGE_C is dropped; so is a step of more than MAX_TEMPERATURE_STEP_C faster
        than MAX_TEMPERATURE_RATE_C_S (a die warms by degrees a minute; Fahrenheit from another
        publisher steps by tens at once) until CONFIRM_SAMPLES in a row agree on the new level
        (a publisher restarted). The reason, the first time it is dropped."""
        series, stamp, (low, high) = self.temperature_series, self._stamp(stamp_ns), \
            TEMPERATURE_RANGE_C
        if not math.isfinite(celsius):
            return None
        problem = None
        if not low <= celsius <= high:
            problem = (f'{celsius:g} degC is outside {low:g} to {high:g} degC (kelvin?); '
                       'sensor_msgs/Temperature is in degrees Celsius')
        elif series.samples and abs(celsius - series.samples[-1][1]) > MAX_TEMPERATURE_STEP_C:
            last_stamp, last = series.samples[-1]
            seconds = max(stamp - last_stamp, 0) / 1e9
            level, count = self._temperature_step
            count = count + 1 if abs(celsius - level) <= MAX_TEMPERATURE_STEP_C else 1
            self._temperature_step = (celsius, count)
            if (abs(celsius - last) > MAX_TEMPERATURE_RATE_C_S * seconds
                    and count < CONFIRM_SAMPLES):
                problem = (f'{celsius:g} degC follows {last:g} degC {seconds:.2g} s before: no '
                           'die warms so fast (two publishers, or degrees Fahrenheit?)')
        if problem is None:
            series.add(stamp, float(celsius))
            self._temperature_step = (math.nan, 0)
            return None
        return series.refuse(f'imu/temperature sample dropped: {problem}')

    def gyro(self, stamp_ns: int, rate: np.ndarray | tuple[float, float, float]) -> None:
        """One gyroscope sample (rad/s, the IMU's frame), integrated into the attitude kept
        readings carry; a gap over GYRO_GAP_NS or a non-finite rate starts a new stretch."""
        x, y, z = (float(value) for value in rate)
        gap = None if self._gyro_stamp is None else stamp_ns - self._gyro_stamp
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            self._stretch += 1
            self._attitude, self._gyro_stamp = None, None
            return
        if gap is not None and gap <= 0:
            return  # a repeated or older stamp
        self._gyro_stamp = stamp_ns
        if self._attitude is None or gap is None or gap > GYRO_GAP_NS:
            self._stretch += 1
            self._attitude = [0.0, 0.0, 0.0, 1.0]
            return
        dt = gap * 1e-9
        angle = math.sqrt(x * x + y * y + z * z) * dt
        if angle == 0.0:
            return
        half = 0.5 * angle
        k = math.sin(half) / (angle / dt)
        bx, by, bz, bw = x * k, y * k, z * k, math.cos(half)
        ax, ay, az, aw = self._attitude  # the body-frame increment on the right
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        qw = aw * bw - ax * bx - ay * by - az * bz
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        self._attitude = [qx / norm, qy / norm, qz / norm, qw / norm]

    def _attitude_at(self, stamp_ns: int) -> tuple[float, ...]:
        """(stretch, quaternion) for a reading now, NaN when the gyroscope is not current."""
        if self._attitude is None or self._gyro_stamp is None or abs(
                stamp_ns - self._gyro_stamp) > GYRO_GAP_NS:
            return NO_ATTITUDE
        return (float(self._stretch), *self._attitude)

    def input(self, index: int, stamp_ns: int | None, value: float,
              calibration: Calibration | None = None, limit: float | None = None) -> str | None:
        """One sample of input ``index``; ``stamp_ns`` None (a message without a header, such as
        Twist) takes the latest reading's stamp. A sample no robot makes
        (``InputSpec.sample_problem``), or one whose own field under the compensation in force
        is beyond ``limit`` (the magnetometer would saturate), is dropped: the reason, the first
        time (one 65535 A "unknown" current published a 0.13 T field, issue #47)."""
        if not 0 <= index < len(self.series):
            return None
        value, spec = float(value), self.specs[index]
        problem = spec.sample_problem(value)
        compensation = None if calibration is None else calibration.compensation
        columns = (None if compensation is None or limit is None
                   else input_columns(compensation.inputs, self.names))
        if problem is None and columns is not None and index in columns:
            field = abs(value) * float(np.max(np.abs(
                compensation.interference[:, columns.index(index)])))
            if not field <= limit:
                problem = (f'{value:g} puts {field:.3g} of own field on the magnetometer under '
                           f'the compensation in force, beyond the {limit:.3g} it reads')
        series = self.series[index]
        if problem is None:
            series.add(self._stamp(stamp_ns), value)
            return None
        return series.refuse(f"interference input '{spec.text}' sample dropped: {problem}")

    def _stamp(self, stamp_ns: int | None) -> int:
        if stamp_ns is not None and stamp_ns > 0:
            return int(stamp_ns)
        return self._last_stamp if self._last_stamp is not None else 0

    def observe(self, stamp_ns: int, reading: np.ndarray, calibration: Calibration | None
                ) -> tuple[np.ndarray, tuple[float, ...]]:
        """The reading without the robot's own field in force (``Calibration.compensated``),
        and its own-field state (``field_of``: what any compensation takes off it); one every
        KEEP_EVERY_S of stream waits (``_settle``) to be kept to learn from once a
        calibration is in force (before it, a robot that stood, then turned to calibrate,
        changed its current with its motion only once, and a K fitted to that step was
        wrong on every axis but one: measured, issue #26)."""
        self._last_stamp = stamp_ns
        temperature = (self.temperature_series.at(stamp_ns, TEMPERATURE_TOLERANCE_NS)
                       if self.use_temperature else math.nan)
        inputs = [series.at(stamp_ns, INPUT_TOLERANCE_NS) for series in self.series]
        for index, value in enumerate((*inputs, temperature)):
            if math.isfinite(value):  # the mean the buffer's readings saw (``carry``)
                self._sums[index] += value
                self._counts[index] += 1
        if self.learning and calibration is not None and stamp_ns / 1e9 >= self._next_keep:
            self._next_keep = stamp_ns / 1e9 + KEEP_EVERY_S
            self._pending.append((stamp_ns, *reading, *self._attitude_at(stamp_ns)))
        if self._pending:
            self._settle()
        held = [value if math.isfinite(value) else series.latest
                for value, series in zip(inputs, self.series, strict=True)]
        if not math.isfinite(temperature) and self.use_temperature:
            temperature = self.temperature_series.latest
        known = self.use_temperature and math.isfinite(temperature)
        state = (*(value if math.isfinite(value) else 0.0 for value in held),
                 temperature if known else 0.0, 1.0 if known else 0.0)
        compensation = None if calibration is None else calibration.compensation
        if compensation is None:
            return reading, state
        ordered = self.in_order_of(compensation.inputs, held)
        return calibration.compensated(reading, ordered if ordered else None,
                                       temperature if self.use_temperature else None), state

    @property
    def state_size(self) -> int:
        """Length of an own-field state (``observe``): the inputs, then the temperature and
        whether it was known."""
        return len(self.series) + 2

    def change(self, old: Compensation | None,
               new: Compensation | None) -> Callable[[np.ndarray], np.ndarray]:
        """What moves a reading compensated by ``old`` to ``new``'s compensation, as a function of
        its own-field states (``SampleBuffer.shift``)."""
        return lambda states: self.field_of(old, states) - self.field_of(new, states)

    def field_of(self, compensation: Compensation | None, states: np.ndarray) -> np.ndarray:
        """What ``compensation`` takes off readings with these own-field states, (n, 3): the
        same as ``observe`` for one reading, and, being linear in the states, for the mean of
        many (a buffered point's merged readings). An input or temperature not known for a
        reading contributes nothing, as in ``Compensation.field``."""
        states = np.asarray(states, dtype=float).reshape(-1, self.state_size)
        total = np.zeros((len(states), 3))
        if compensation is None:
            return total
        count = len(self.series)
        columns = input_columns(compensation.inputs, self.names)
        if columns is not None and len(columns):
            total += states[:, columns] @ compensation.interference.T
        if compensation.reference_temperature is not None:
            drift = states[:, count] - states[:, count + 1] * compensation.reference_temperature
            total += np.multiply.outer(drift, compensation.temperature_coefficient)
        return total

    def _settle(self) -> None:
        """Keep the waiting readings whose inputs' samples are there (one stamped at or after
        the reading: a callback may run after the reading's under load, and a reading paired
        with the sample before a current step would teach a fraction of K), or that waited
        while PENDING others came; all inputs fresh, one in HOLD_OUT_EVERY held out."""
        while self._pending:
            stamp_ns = self._pending[0][0]
            if len(self._pending) <= PENDING and any(
                    not series.samples or series.samples[-1][0] < stamp_ns
                    for series in self.series):
                return
            stamp_ns, x, y, z, *attitude = self._pending.popleft()
            temperature = (self.temperature_series.at(stamp_ns, TEMPERATURE_TOLERANCE_NS)
                           if self.use_temperature else math.nan)
            inputs = [series.at(stamp_ns, INPUT_TOLERANCE_NS) for series in self.series]
            if all(math.isfinite(value) for value in inputs) and (
                    math.isfinite(temperature) or not self.temperature_series.received
                    or not self.use_temperature):
                self._count += 1
                row = (stamp_ns / 1e9, x, y, z, temperature, *attitude, *inputs)
                (self._held if self._count % HOLD_OUT_EVERY == 0 else self._kept).append(row)

    def in_order_of(self, names: tuple[str, ...], values: list[float]) -> list[float]:
        """This node's input values in the order of a compensation's ``names``: by name when it
        subscribes them all, else by position when the counts agree (a file learnt offline
        names its columns); a term with no input here contributes nothing (NaN), said in
        ``diagnostic_values`` as ``interference_unmatched``."""
        columns = input_columns(names, self.names)
        if columns is None:
            self.unmatched = names
            return [math.nan] * len(names)
        return [values[column] for column in columns]

    # -- fits ----------------------------------------------------------------------------------

    def due(self, now: float, calibration: Calibration | None) -> str | None:
        """'compensate' when a compensation fit should run now (something to learn, enough
        kept), else None."""
        if (not self.learning or calibration is None or now < self._next_fit
                or len(self._kept) < MIN_READINGS or not self._held):
            return None
        if not self.specs and not (self.use_temperature and self.temperature_series.received):
            return None
        self._next_fit = now + (LEARN_PERIOD_S if self._window is None else QUICK_PERIOD_S)
        return 'compensate'

    def data(self, calibration: Calibration) -> CompensationData:
        """The kept readings as one fit's input; T0 is the one in force, when there is one."""
        kept, held = self._kept.copy(), self._held.copy()
        compensation = calibration.compensation
        with_temperature = self.use_temperature and self.temperature_series.received > 0
        term = None
        if self._window is not None and self.specs:  # K only; the drift in force stays
            with_temperature = False
            if compensation is not None and compensation.reference_temperature is not None:
                term = (tuple(compensation.temperature_coefficient),
                        compensation.reference_temperature)
                kept, held = (_without_drift(rows, *term) for rows in (kept, held))
        if with_temperature:
            # Readings kept before the first temperature sample came have none (it comes on
            # another topic, and a loaded computer can deliver it after the first readings):
            # the fit leaves those readings out, not the temperature, which one such reading
            # used to keep out of every fit (and bias K with its drift, issue #22).
            known_kept, known_held = np.isfinite(kept[:, 4]), np.isfinite(held[:, 4])
            with_temperature = (int(known_kept.sum()) >= MIN_READINGS
                                and bool(known_held.any()))
            if with_temperature:
                kept, held = kept[known_kept], held[known_held]
        t0 = None if compensation is None else compensation.reference_temperature
        gyroscope = bool(np.any(np.isfinite(kept[:, 5])))
        return CompensationData(
            kept[:, 1:4], kept[:, ROW_INPUTS:], kept[:, 4] if with_temperature else None,
            self.names,
            held[:, 1:4], held[:, ROW_INPUTS:], held[:, 4] if with_temperature else None, t0,
            kept[:, 0], kept[:, 5:10] if gyroscope else None,
            held[:, 0], held[:, 5:10] if gyroscope else None,
            self._anchor_for_fits(), self.anchor_unknown, term)

    def _anchor_for_fits(self) -> np.ndarray | None:
        """``~/learn_compensation``'s fits hold the offset at the whole anchor; live fits only
        where the compensation in force covers a term (exact), else at their readings' mean:
        those span headings and the warm-up, and holding it at a cold start's temperature
        pulled c 11-14 % off (bench_interference, seeds 2 and 3)."""
        if self.anchor is None or len(self.anchor) != len(self.series) + 1:
            return None
        if self._window is not None:
            return self.anchor
        return np.where(self.covered, self.anchor, math.nan) if self.covered.any() else None

    def job(self, calibration: Calibration) -> FitJob:
        """The next compensation fit, on the calibration in force."""
        empty = np.zeros((0, 3))
        return FitJob('compensate', empty, None, None, REFERENCE_OPTIONS, current=calibration,
                      compensation=self.data(calibration))

    def judged(self, outcome: JobOutcome, current: Calibration | None) -> Verdict:
        """The verdict on a finished compensation fit (``verdicts.compensation_verdict``)."""
        self.last_fit = outcome.compensation
        return compensation_verdict(outcome, current)

    def carry(self, calibration: Calibration, previous: Calibration | None,
              source: str) -> Calibration:
        """A static fit put in force keeps the compensation in force (its readings were
        compensated by it); a file, parameters or a learned compensation bring their own.
        Notes, term by term, where the new calibration is right for raw readings (``anchor``),
        which is where the fits hold the offset: for a term its compensation has (K's column
        not zero, c with its T0), at zero input (at T0), and every fit holds it there
        (``covered``); for another, a static fit's at the mean of the readings since the
        buffer was last emptied, a learned compensation's where the one before it was, a
        static file's or parameters' unknown (``anchor_unknown``: the next fits find it).
        'realign' and 'tracking' keep the offset, and so the anchor."""
        if source not in ('file', 'parameters', 'given', 'compensation'):
            calibration = kept_compensation(calibration, previous)
        if source in ('realign', 'tracking'):
            return calibration
        terms = len(self.series) + 1
        if source in ('file', 'parameters', 'given'):
            elsewhere, self._from_file = np.full(terms, math.nan), True
        elif source == 'compensation':
            elsewhere = (np.full(terms, math.nan) if self.anchor is None
                         or len(self.anchor) != terms else self.anchor)
        else:
            self._from_file = False
            elsewhere = np.array([total / count if count else math.nan
                                  for total, count in zip(self._sums, self._counts,
                                                          strict=True)])
        self.covered = covered_terms(calibration.compensation, self.names)
        zero = np.zeros(terms)
        if calibration.compensation is not None and self.covered[-1]:
            zero[-1] = calibration.compensation.reference_temperature  # type: ignore[assignment]
        self.anchor = np.where(self.covered, zero, elsewhere)
        return calibration

    @property
    def anchor_unknown(self) -> bool:
        """The calibration in force came from a file or parameters and some term's anchor is
        unknown, so fits find it (``CompensationData.anchor_unknown``)."""
        return (self._from_file and self.anchor is not None
                and bool(np.isnan(self.anchor).any()))

    # -- the quick procedure: ~/learn_compensation ----------------------------------------------

    @property
    def learning(self) -> bool:
        """Whether readings are kept and fits run: ``learn_compensation``, or a window open."""
        return self.learn or self._window is not None

    def open_window(self, ticket: int, now: float, timeout_s: float,
                    calibration: Calibration | None, units: str = 'T') -> str:
        """Learn now, a fit every QUICK_PERIOD_S of stream, until one goes in force or
        ``timeout_s`` of stream pass (ArduPilot's compassmot, but live: the motors run through
        several currents, on a stand or driving straight); '' or why it cannot start."""
        if calibration is None:
            return ("no calibration in force: the robot's own field is learned on one "
                    '(calibrate first: ~/calibrate, ~/rotate_and_calibrate or ~/load)')
        if not self.specs and not self.use_temperature:
            return ('nothing to learn: interference_inputs is empty and use_temperature is '
                    "false (list the robot's currents or speeds in interference_inputs)")
        if not self.specs and not self.temperature_series.samples:
            return ('nothing to learn: interference_inputs is empty and no die temperature has '
                    "come on imu/temperature (list the robot's currents or speeds in "
                    'interference_inputs)')
        if not (math.isfinite(timeout_s) and 0.0 < timeout_s <= MAX_WINDOW_S):
            return f'compensation_timeout must be in (0, {MAX_WINDOW_S:g}] s, got {timeout_s}'
        if self._window is not None:
            return 'already learning: another ~/learn_compensation is waiting for its answer'
        self._window = _Window(ticket, now, now + timeout_s, units)
        self._next_fit = now
        return ''

    def window_answer(self, now: float, calibration: Calibration | None,
                      verdict: Verdict | None = None) -> tuple[int, CalibrationAttempt] | None:
        """The open window's answer once there is one (None: not yet). A compensation put in
        force (``verdict``) is fitted again on more readings, QUICK_PERIOD_S later, until a fit
        that determines its terms is no better (converged: the answer) or the window ends (the
        latest learned, else what the latest fit needed). A first one learned from the first
        current step would otherwise answer with a K that the next steps still move."""
        window = self._window
        if window is None:
            return None
        fit = self.last_fit
        if verdict is not None:
            if verdict.adopt is not None and verdict.source == 'compensation':
                coefficients = '; '.join(
                    f'{key} {value}' for key, value in coefficient_values(
                        verdict.adopt.compensation, window.units).items())
                window.learned = (f'learned in {now - window.opened:.1f} s of readings: '
                                  f'{coefficients}. {verdict.message}')
                window.learned_at = now
                return None
            if window.learned and verdict.message and fit is not None \
                    and fit.calibration is not None and fit.kept:
                return self._close(True, f'{window.learned}; converged: a fit with '
                                         f'{now - window.learned_at:.0f} s more of readings is '
                                         'no better')
            window.latest = verdict.message or window.latest
        if now < window.deadline:
            return None
        if window.learned:
            return self._close(True, window.learned)
        span = f'{window.deadline - window.opened:g} s of readings'
        if window.latest and fit is not None and fit.calibration is not None and fit.kept \
                and calibration is not None and calibration.compensation is not None:
            return self._close(True, f'the compensation in force stays: what {span} determined '
                                     f'is no better ({window.latest})')
        if not window.latest:
            kept = len(self._kept) + len(self._held)
            if not self.learn and (window.deadline - window.opened) / KEEP_EVERY_S < 1.2 * (
                    MIN_READINGS + MIN_READINGS // HOLD_OUT_EVERY):
                return self._close(False, (
                    f'nothing learned in {span}: it keeps {1 / KEEP_EVERY_S:g} readings a '
                    f'second ({kept} here) and a fit needs {MIN_READINGS} besides those held '
                    f'out: make compensation_timeout longer (15 s at least)'))
            inputs = ', '.join(self.names) or 'imu/temperature'
            return self._close(False, f'nothing learned in {span}: {kept} readings were kept '
                                      f'with their inputs and a fit needs {MIN_READINGS}; is '
                                      f'every input published ({inputs})?')
        why = fit.reason if fit is not None and fit.calibration is None else ''
        return self._close(False, f'nothing learned in {span}: {why or window.latest}')

    def close_window(self, reason: str) -> tuple[int, CalibrationAttempt] | None:
        """End an open window now, unanswered until here (a reset, the node giving up)."""
        return None if self._window is None else self._close(False, reason)

    def _close(self, success: bool, message: str) -> tuple[int, CalibrationAttempt]:
        ticket, self._window = self._window.ticket, None
        if not self.learn:  # kept for the window only
            self._kept.clear()
            self._held.clear()
            self._pending.clear()
        return ticket, CalibrationAttempt(success, message)

    # -- reports -------------------------------------------------------------------------------

    def needs(self) -> str:
        """What motion or wait the latest fit needed to determine a term ('' if none)."""
        fit = self.last_fit
        if fit is None:
            return ''
        return '; '.join(term.need for term in fit.terms if term.need)

    def silence_note(self, calibration: Calibration | None) -> str:
        """Which inputs the compensation in force applies are silent (SILENT_INTERVALS), held at
        their last value: a field that then departs may be theirs, not a magnet's (issue #47:
        a driver that stopped kept its last current for good, and the misfit blamed the world).
        '' when none is."""
        compensation = None if calibration is None else calibration.compensation
        columns = None if compensation is None else input_columns(compensation.inputs,
                                                                  self.names)
        notes = []
        for index in columns or ():
            series = self.series[index]
            gap = series.silent_for(self._last_stamp or 0)
            if gap is not None:
                notes.append(f"interference input '{self.specs[index].text}' has sent nothing "
                             f'for {gap:.0f} s: its own field is held at its last value, '
                             f'{series.latest:g}')
        return '; '.join(notes)

    def diagnostic_values(self, calibration: Calibration | None, units: str = 'T',
                          now: float = 0.0) -> dict[str, object]:
        """K, c, T0, the share removed and when it was learned; what is still needed."""
        values: dict[str, object] = {}
        if self.specs:
            values['interference_inputs'] = ', '.join(self.names)
        if self.unmatched and calibration is not None and calibration.compensation is not None \
                and calibration.compensation.inputs == self.unmatched:
            values['interference_unmatched'] = (
                f"the calibration compensates {', '.join(self.unmatched)}, which "
                'interference_inputs does not list: those terms are not applied (list them in '
                'the same order)')
        silence = self.silence_note(calibration)
        if silence:
            values['interference_silent'] = silence
        if self.temperature_series.received:
            values['temperature_degC'] = round(self.temperature_series.latest, 2)
        compensation = None if calibration is None else calibration.compensation
        if compensation is not None:
            values.update(coefficient_values(compensation, units))
            if compensation.reference_temperature is not None:
                values['reference_temperature_degC'] = compensation.reference_temperature
            for key in LEARNED:
                if key in calibration.metadata:
                    values[key] = calibration.metadata[key]
            interference = calibration.metadata_number('compensation_interference_pct')
            if interference is not None:
                values['interference_scale'] = interference_grade(interference)
        if self._window is not None:
            values['compensation_learning'] = (
                f'~/learn_compensation: {max(self._window.deadline - now, 0.0):.0f} s left')
        if self.learning and (self.specs or self.temperature_series.received):
            values['compensation_readings_kept'] = len(self._kept) + len(self._held)
            need = self.needs()
            if need:
                values['compensation_needs'] = need
        return values


def coefficient_values(compensation: Compensation | None, units: str = 'T'
                       ) -> dict[str, list[float]]:
    """K per input and c, named with their units (microtesla in the nodes, whose readings are
    in tesla; a recording's own units offline), for /diagnostics and the answers."""
    if compensation is None:
        return {}
    scale, unit = (1e6, 'uT') if units == 'T' else (1.0, units)
    values = {f'interference_{unit}_per_unit[{name}]': [
        round(float(value) * scale, 4) for value in compensation.interference[:, j]]
        for j, name in enumerate(compensation.inputs)}
    values[f'temperature_coefficient_{unit}_per_degC'] = [
        round(float(value) * scale, 4) for value in compensation.temperature_coefficient]
    return values


__all__ = ['LEARNED', 'TEMPERATURE', 'CompensationLearner', 'coefficient_values',
           'covered_terms', 'input_columns']
