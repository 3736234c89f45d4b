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
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.compensation import (
    LEARNED,
    MIN_READINGS,
    TEMPERATURE,
    CompensationData,
)
from mag_calibrator_ros.calibration.live.inputs import InputSpec, parse_input
from mag_calibrator_ros.calibration.live.jobs import REFERENCE_OPTIONS, FitJob, JobOutcome
from mag_calibrator_ros.calibration.live.verdicts import Verdict, compensation_verdict

SAMPLE_RING = 32
"""Recent samples of each input and of the temperature, to pair readings with by stamp."""
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
HOLD_OUT_EVERY = 5
LEARN_PERIOD_S = 10.0
"""Stream seconds between compensation fits while there is something to learn."""
PENDING = 40
"""Readings waiting for their inputs' samples, at most (one every KEEP_EVERY_S: 2 s of stream);
the oldest is then paired with the sample nearest it within INPUT_TOLERANCE_NS, or dropped."""
GYRO_GAP_NS = 100_000_000
"""A longer gap between gyroscope samples (or a non-finite one) ends a stretch of integrated
attitude: the rotation across it is not known, so no readings across it are compared."""
NO_ATTITUDE = (math.nan,) * 5


class _Series:
    """Recent (stamp, value) samples of one input; nearest by stamp, O(ring) from the newest."""

    def __init__(self) -> None:
        self.samples: deque[tuple[int, float]] = deque(maxlen=SAMPLE_RING)
        self.latest = math.nan
        self.received = 0

    def add(self, stamp_ns: int, value: float) -> None:
        if math.isfinite(value):
            self.samples.append((stamp_ns, value))
            self.latest = value
            self.received += 1

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
        self.reset()
        self.configure(inputs, use_temperature, learn)
        self.last_fit = None
        """The latest CompensationFit (reports: what each term needs)."""
        self.last_learned = ''
        """What the latest adopted compensation changed, for the log and /diagnostics."""

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
        self._kept: deque[tuple[float, ...]] = deque(maxlen=KEPT)
        self._held: deque[tuple[float, ...]] = deque(maxlen=HELD)
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

    # -- per message (O(k)) --------------------------------------------------------------------

    def temperature(self, stamp_ns: int | None, celsius: float) -> None:
        """One ``sensor_msgs/Temperature`` sample (degrees Celsius); implausible ones dropped."""
        if math.isfinite(celsius) and -60.0 <= celsius <= 200.0:
            self.temperature_series.add(self._stamp(stamp_ns), float(celsius))

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

    def input(self, index: int, stamp_ns: int | None, value: float) -> None:
        """One sample of input ``index``; ``stamp_ns`` None (a message without a header, such as
        Twist) takes the latest reading's stamp."""
        if 0 <= index < len(self.series):
            self.series[index].add(self._stamp(stamp_ns), float(value))

    def _stamp(self, stamp_ns: int | None) -> int:
        if stamp_ns is not None and stamp_ns > 0:
            return int(stamp_ns)
        return self._last_stamp if self._last_stamp is not None else 0

    def observe(self, stamp_ns: int, reading: np.ndarray, calibration: Calibration | None
                ) -> np.ndarray:
        """The reading without the robot's own field in force (``Calibration.compensated``);
        one every KEEP_EVERY_S of stream waits (``_settle``) to be kept to learn from."""
        self._last_stamp = stamp_ns
        temperature = (self.temperature_series.at(stamp_ns, TEMPERATURE_TOLERANCE_NS)
                       if self.use_temperature else math.nan)
        inputs = [series.at(stamp_ns, INPUT_TOLERANCE_NS) for series in self.series]
        if self.learn and calibration is not None and stamp_ns / 1e9 >= self._next_keep:
            self._next_keep = stamp_ns / 1e9 + KEEP_EVERY_S
            self._pending.append((stamp_ns, *reading, *self._attitude_at(stamp_ns)))
        if self._pending:
            self._settle()
        compensation = None if calibration is None else calibration.compensation
        if compensation is None:
            return reading
        held = self.in_order_of(compensation.inputs, [
            value if math.isfinite(value) else series.latest
            for value, series in zip(inputs, self.series, strict=True)])
        if not math.isfinite(temperature) and self.use_temperature:
            temperature = self.temperature_series.latest
        return calibration.compensated(reading, held if held else None,
                                       temperature if self.use_temperature else None)

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
        own = self.names
        if tuple(names) == own:
            return values
        if all(name in own for name in names):
            return [values[own.index(name)] for name in names]
        if len(names) == len(own):
            return values
        self.unmatched = names
        return [math.nan] * len(names)

    # -- fits ----------------------------------------------------------------------------------

    def due(self, now: float, calibration: Calibration | None) -> str | None:
        """'compensate' when a compensation fit should run now (something to learn, enough
        kept), else None."""
        if (not self.learn or calibration is None or now < self._next_fit
                or len(self._kept) < MIN_READINGS or not self._held):
            return None
        if not self.specs and not (self.use_temperature and self.temperature_series.received):
            return None
        self._next_fit = now + LEARN_PERIOD_S
        return 'compensate'

    def data(self, calibration: Calibration) -> CompensationData:
        """The kept readings as one fit's input; T0 is the one in force, when there is one."""
        kept, held = np.array(self._kept), np.array(self._held)
        with_temperature = self.use_temperature and self.temperature_series.received > 0
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
        compensation = calibration.compensation
        t0 = None if compensation is None else compensation.reference_temperature
        gyroscope = bool(np.any(np.isfinite(kept[:, 5])))
        return CompensationData(
            kept[:, 1:4], kept[:, 10:], kept[:, 4] if with_temperature else None, self.names,
            held[:, 1:4], held[:, 10:], held[:, 4] if with_temperature else None, t0,
            kept[:, 0], kept[:, 5:10] if gyroscope else None,
            held[:, 0], held[:, 5:10] if gyroscope else None)

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
        compensated by it); a file, parameters or a learned compensation bring their own."""
        if (source in ('file', 'parameters', 'given', 'compensation') or previous is None
                or previous.compensation is None or calibration.compensation is not None):
            return calibration
        learned = {key: previous.metadata[key] for key in LEARNED if key in previous.metadata}
        return calibration.with_compensation(previous.compensation, **learned)

    # -- reports -------------------------------------------------------------------------------

    def needs(self) -> str:
        """What motion or wait the latest fit needed to determine a term ('' if none)."""
        fit = self.last_fit
        if fit is None:
            return ''
        return '; '.join(term.need for term in fit.terms if term.need)

    def diagnostic_values(self, calibration: Calibration | None, units: str = 'T'
                          ) -> dict[str, object]:
        """K, c, T0, the share removed and when it was learned; what is still needed."""
        scale, unit = (1e6, 'uT') if units == 'T' else (1.0, units)
        values: dict[str, object] = {}
        if self.specs:
            values['interference_inputs'] = ', '.join(self.names)
        if self.unmatched and calibration is not None and calibration.compensation is not None \
                and calibration.compensation.inputs == self.unmatched:
            values['interference_unmatched'] = (
                f"the calibration compensates {', '.join(self.unmatched)}, which "
                'interference_inputs does not list: those terms are not applied (list them in '
                'the same order)')
        if self.temperature_series.received:
            values['temperature_degC'] = round(self.temperature_series.latest, 2)
        compensation = None if calibration is None else calibration.compensation
        if compensation is not None:
            for j, name in enumerate(compensation.inputs):
                values[f'interference_{unit}_per_unit[{name}]'] = [
                    round(float(value) * scale, 4) for value in compensation.interference[:, j]]
            values[f'temperature_coefficient_{unit}_per_degC'] = [
                round(float(value) * scale, 4) for value in compensation.temperature_coefficient]
            if compensation.reference_temperature is not None:
                values['reference_temperature_degC'] = compensation.reference_temperature
            for key in LEARNED:
                if key in calibration.metadata:
                    values[key] = calibration.metadata[key]
        if self.learn and (self.specs or self.temperature_series.received):
            values['compensation_readings_kept'] = len(self._kept) + len(self._held)
            need = self.needs()
            if need:
                values['compensation_needs'] = need
        return values


__all__ = ['LEARNED', 'TEMPERATURE', 'CompensationLearner']
