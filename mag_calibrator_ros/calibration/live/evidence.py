# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Held-out evidence: readings no fit has seen, and the two judgements made on them.

A calibration fitted to the buffer always looks good on the buffer. To know whether a new fit is
really better than the calibration in force, and whether the calibration in force still fits the
sensor, the session holds some readings back from the buffer (every ``HOLD_OUT_EVERY``-th) and
judges on those:

- ``compare_on_evidence``: is a candidate better than the calibration in force, by a margin beyond
  noise? A paired test on the same readings (each reading's capped squared residual under both),
  robust to the spikes and disturbances a live stream has.
- ``MisfitMonitor``: does the calibration in force still fit? Recent evidence spanning directions
  whose corrected magnitude is clearly off, for several seconds: another sensor's file, a new
  payload, a re-mounted sensor -- not a magnet passing by.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import (
    CELL_COUNT,
    HEADING_SECTORS,
    cell_index,
    direction_coverage,
    sector_of,
)
from mag_calibrator_ros.calibration.fit.ellipsoid import robust_sigma
from mag_calibrator_ros.calibration.fit.heading import heading_coverage_of, yaw_only
from mag_calibrator_ros.calibration.live.buffer import moves_of

HOLD_OUT_EVERY = 4
"""While a calibration is in force, one accepted reading in four (a deterministic pseudo-random
draw) is evidence instead of a buffer sample: enough to judge on within seconds of moving, while
the buffer, which keeps the most spread-out points anyway, loses little (before the first
calibration nothing is held out: there is nothing to judge yet)."""

READINGS_PER_CELL = 32
"""Evidence is kept per direction cell (the latest 32 in each of the 80, at most 2,560 readings,
60 kB): a robot that stands still refreshes one cell and the rest stay, so judgements always
span the directions seen. The standard error of a paired comparison falls as one over the root
of the readings: with eight a cell, real gains of 3-5 % on a 2 %-noise sensor stayed below three
standard errors however long the sensor turned (the live output stayed 3 % worse than what
``~/calibrate`` gave); four times as many halve the gain that can be proven."""

MIN_EVIDENCE = 30
"""Fewer held-out readings than this decide nothing."""

MIN_EVIDENCE_SPAN = 0.25
"""Share of direction cells the evidence must span (judged by its own shape, not through the
calibration under test; yaw-only, also about the centre either calibration puts it round,
``span_about``) before a candidate may replace the calibration in force: better in one corner
of the sphere is not better."""
THIN_CELLS = 64
"""A heading circle's span is judged on one reading per 1/64 of their extent (about 1 uT of a
50 uT field): where readings piled up says nothing of the headings they span (``_thinned``)."""

SIGNIFICANCE = 3.0
"""A candidate must beat the calibration in force by three standard errors of the paired
difference (one-sided: about 1 in 700 by chance alone). Two would prove more real improvements
sooner, but lets a measurably worse candidate through when a quarter of the held-out readings
is disturbed (found by the property test); real first calibrations from half the sphere are
beaten at 3-9 standard errors within a few hundred messages (benchmarks/bench_replay.py)."""

MIN_GAIN = 0.02
"""...and by at least 2 % of its residual, so that many readings of a tiny gain cause no churn."""

TIME_STRETCHES = 9
"""...and still better once the four of nine stretches of time most in its favour are left out
(the held-out readings in stream order, split evenly). A disturbance that lasts a while (a
magnet passing, a motor running) can favour a worse candidate by far more than the standard
error of many readings, and the more readings, the smaller that error; one that lasts up to 30 %
of the time touches at most four of nine stretches, and the five others show the candidate as it
is (found by the property test on a full store of held-out readings). A real gain shows in every
stretch, so leaving out the best four costs it little."""

FAVOURED_STRETCHES = 4

GROSS_ERROR = 0.3
"""A reading off by more than 30 % under both calibrations is a spike or a magnet: left out."""

CAP_SIGMAS = 3.0
"""Each reading's loss is its squared residual capped at three noise sigmas: a reading that
neither calibration explains (a spike, a magnet passing) costs both the same and decides
nothing, and no single reading can decide more than a cap's worth."""


class HeldOutEvidence:
    """Held-out readings, the latest few per direction cell, each with its stream time and
    its state (as ``SampleBuffer``'s: what was taken off it, for ``shift``)."""

    def __init__(self, per_cell: int = READINGS_PER_CELL) -> None:
        self._per_cell = per_cell
        size = CELL_COUNT * per_cell
        self._readings = np.zeros((size, 3))
        self._times = np.full(size, -math.inf)
        self._valid = np.zeros(size, dtype=bool)
        self._next = np.zeros(CELL_COUNT, dtype=int)  # ring position within each cell
        self.forget_states(0)

    def add(self, reading: np.ndarray, direction: np.ndarray, time_s: float,
            state: Sequence[float] | None = None) -> None:
        """Keep ``reading`` in the cell of ``direction`` (any non-zero vector)."""
        direction = direction / np.max(np.abs(direction))  # a norm of tiny values underflows
        cell = int(cell_index(direction.reshape(1, 3) / np.linalg.norm(direction))[0])
        slot = cell * self._per_cell + int(self._next[cell])
        self._next[cell] = (self._next[cell] + 1) % self._per_cell
        self._readings[slot] = reading
        self._times[slot] = time_s
        self._valid[slot] = True
        self._states[slot] = math.nan if state is None else state

    def forget_states(self, size: int) -> None:
        """States from now on have ``size`` values; those held are unknown."""
        self._states = np.full((len(self._readings), int(size)), math.nan)

    def shift(self, change: Callable[[np.ndarray], np.ndarray]) -> None:
        """Move each reading by ``change(states)`` ((n, size) to (n, 3)); one that cannot
        move (an unknown state) is dropped. It stays in its direction cell: a shift is a small
        part of the field."""
        valid = np.flatnonzero(self._valid)
        moves, movable = moves_of(change, self._states[valid])
        self._readings[valid[movable]] += moves[movable]
        self._valid[valid[~movable]] = False

    def __len__(self) -> int:
        return int(self._valid.sum())

    def readings(self, since_s: float = -math.inf) -> np.ndarray:
        """Held-out readings (n, 3) no older than ``since_s`` (stream seconds), oldest first
        (``compare_on_evidence`` judges stretches of time), a copy."""
        keep = np.flatnonzero(self._valid & (self._times >= since_s))
        return self._readings[keep[np.argsort(self._times[keep], kind='stable')]]

    def forget_before(self, time_s: float) -> None:
        """Drop what was held out before ``time_s``: it describes a situation that has ended."""
        self._valid &= self._times >= time_s

    def forget_between(self, start_s: float, end_s: float) -> None:
        """Drop what was held out from ``start_s`` until ``end_s``: readings of a disturbance."""
        self._valid &= (self._times < start_s) | (self._times >= end_s)

    def clear(self) -> None:
        self._valid[:] = False


def relative_errors(calibration: Calibration, readings: np.ndarray,
                    inputs: np.ndarray | None = None,
                    temperatures: np.ndarray | None = None) -> np.ndarray:
    """``|corrected| / F - 1`` for each reading (with its interference inputs and temperature,
    when given: ``Calibration.apply``)."""
    corrected = calibration.apply(readings, inputs, temperatures)
    return np.linalg.norm(corrected / calibration.field_strength, axis=1) - 1.0  # no underflow


def magnitude_residual_pct(calibration: Calibration, samples: np.ndarray) -> float:
    """RMS of ``|corrected| - F`` as a percentage of F: the engine's residual measure."""
    if len(samples) == 0:
        return math.inf
    return float(100.0 * np.sqrt(np.mean(relative_errors(calibration, samples) ** 2)))


def evidence_span(readings: np.ndarray, minimum: int = MIN_EVIDENCE) -> float:
    """Share of direction cells the readings span, judged by their own shape (centred and
    whitened by themselves), so a calibration that is badly off cannot hide their spread. Readings
    of a robot turning about one axis span the heading circle, not the sphere: their share of
    heading sectors (on their own ring) counts then, or a ground robot could never be judged."""
    if len(readings) < minimum:
        return 0.0
    if yaw_only(readings):
        return float(heading_coverage_of(_thinned(readings)).coverage.fraction)
    return float(direction_coverage(readings, None, readings).fraction)


def span_about(calibration: Calibration, readings: np.ndarray) -> float | None:
    """Share of heading sectors yaw-only ``readings`` span about the centre ``calibration`` puts
    them round (their headings as it corrects them, in the plane they lie in), or None when
    they are not yaw-only. Their own ring (``evidence_span``) can be fooled: a short arc of a
    turn and a straight leg's readings, smeared by the robot's own field, fit a small circle
    that spans a third of the headings; about a centre that no reading moved, they span what
    they span (stop 33's follow-up, found again through bench_interference's quick procedure)."""
    corrected = calibration.apply(np.asarray(readings, dtype=float).reshape(-1, 3))
    corrected = corrected[np.all(np.isfinite(corrected), axis=1)]
    if len(corrected) < MIN_EVIDENCE or not yaw_only(corrected):
        return None
    thinned = _thinned(corrected)
    _, _, axes = np.linalg.svd(thinned - thinned.mean(axis=0))  # 3 axes from 2 rows too
    headings = np.arctan2(thinned @ np.cross(axes[2], axes[0]), thinned @ axes[0])
    return len(np.unique(sector_of(headings))) / HEADING_SECTORS


def _thinned(readings: np.ndarray) -> np.ndarray:
    """One reading per cell of a grid THIN_CELLS to their extent: a robot that stood, or drove
    one way, most of the time leaves a cluster that outweighs its turns in any fit of their own
    shape (``fit_ring`` centres and scales by medians), though it adds no direction."""
    readings = np.asarray(readings, dtype=float).reshape(-1, 3)
    readings = readings[np.all(np.isfinite(readings), axis=1)]
    extent = float(np.max(np.ptp(readings, axis=0))) if len(readings) else 0.0
    if not extent > 0.0:
        return readings
    _, first = np.unique(np.floor(readings * (THIN_CELLS / extent)), axis=0, return_index=True)
    return readings[np.sort(first)]


@dataclass(frozen=True)
class Comparison:
    """A candidate against the calibration in force on the same held-out readings."""

    better: bool
    current_pct: float
    candidate_pct: float
    readings: int
    span: float
    reason: str

    @property
    def gain_pct(self) -> float | None:
        """How much lower the candidate's residual is than the current one's, in percent of the
        current one (negative when it is worse); None when too few readings said anything."""
        if self.readings < MIN_EVIDENCE or not (
                math.isfinite(self.current_pct) and self.current_pct > 0.0):
            return None
        return 100.0 * (1.0 - self.candidate_pct / self.current_pct)


def compare_on_evidence(
    current: Calibration, candidate: Calibration, evidence: np.ndarray,
    inputs: np.ndarray | None = None, temperatures: np.ndarray | None = None,
) -> Comparison:
    """Whether ``candidate`` fits ``evidence`` better than ``current`` by a margin beyond noise.

    Residuals are ``|corrected|/F - 1``; readings off by more than GROSS_ERROR under both are left
    out; each remaining reading contributes its squared residual capped at CAP_SIGMAS of the
    better calibration's robust noise, under both, and the candidate wins when the mean paired
    difference exceeds SIGNIFICANCE standard errors and MIN_GAIN of the current residual, and
    is positive without the FAVOURED_STRETCHES of TIME_STRETCHES (``evidence`` in stream order,
    as ``HeldOutEvidence`` gives it) most in the candidate's favour. Raw readings with inputs
    span what they span as either calibration corrects them: the own field moves raw readings
    off their ring by ``K u``, and their own shape (``evidence_span``) then tells nothing; a
    compensation moves readings along its inputs' field only, so it adds no headings. They
    judge it only where the two calibrations' magnitudes differ by at least the candidate's
    typical error (as held-out gyroscope pairs do): a drift learned as the die warmed leaves
    the earlier readings as they were, and stretches of time in which both agree read as
    'better only in some stretches' for a minute and more. That choice depends on the inputs
    and headings, never on which one fits.
    Residuals are reported as percent (square root of the mean capped loss: the RMS when nothing
    is disturbed). Raw readings with their ``inputs`` and ``temperatures`` judge a learned
    compensation (``live/compensation.py``) by the same rule.
    """
    evidence = np.asarray(evidence, dtype=float).reshape(-1, 3)
    now, new = (relative_errors(calibration, evidence, inputs, temperatures)
                for calibration in (current, candidate))
    keep = (np.abs(now) <= GROSS_ERROR) | (np.abs(new) <= GROSS_ERROR)
    now, new = now[keep], new[keep]
    what = 'held-out readings'
    if inputs is None and temperatures is None:
        span = evidence_span(evidence[keep])
        about = [span_about(calibration, evidence[keep]) for calibration in (current, candidate)]
        if None not in about:  # yaw-only: spread about the centre either calibration puts
            span = min(span, max(about))
    else:  # raw readings the robot's own field moved off their ring: their span as corrected
        span = max(evidence_span(calibration.apply(evidence, inputs, temperatures)[keep])
                   for calibration in (current, candidate))
        telling = np.abs(now - new) >= float(np.median(np.abs(new)))  # see above
        now, new = now[telling], new[telling]
        what = 'held-out readings that tell them apart'
    n = len(now)
    if n < MIN_EVIDENCE:
        return Comparison(False, math.nan, math.nan, n, span,
                          f'{n} {what}, need {MIN_EVIDENCE}')
    loss_now, loss_new, current_pct, candidate_pct = _capped_losses(now, new)
    if span < MIN_EVIDENCE_SPAN:
        return Comparison(False, current_pct, candidate_pct, n, span,
                          f'held-out readings span {100 * span:.0f} % of the directions, need '
                          f'{100 * MIN_EVIDENCE_SPAN:.0f} %')
    return _judged(loss_now, loss_new, current_pct, candidate_pct, span, what)


def compare_residuals(now: np.ndarray, new: np.ndarray, what: str) -> Comparison:
    """``compare_on_evidence``'s rule on residuals (relative to F) computed elsewhere, in stream
    order, without its span of directions: the held-out pairs of readings a learned
    compensation is judged on through the gyroscope (``fit/compensation.py`` pair_errors)."""
    now, new = np.asarray(now, dtype=float), np.asarray(new, dtype=float)
    keep = (np.abs(now) <= GROSS_ERROR) | (np.abs(new) <= GROSS_ERROR)
    now, new = now[keep], new[keep]
    if len(now) < MIN_EVIDENCE:
        return Comparison(False, math.nan, math.nan, len(now), math.nan,
                          f'{len(now)} {what}, need {MIN_EVIDENCE}')
    return _judged(*_capped_losses(now, new), math.nan, what)


def _capped_losses(now: np.ndarray, new: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Squared residuals capped at CAP_SIGMAS of the better one's robust noise, and their RMS
    in percent."""
    sigma_now, sigma_new = (robust_sigma(r, about_median=True, floor=None) for r in (now, new))
    cap = (CAP_SIGMAS * max(min(sigma_now, sigma_new), 1e-9)) ** 2
    loss_now, loss_new = np.minimum(now**2, cap), np.minimum(new**2, cap)
    return (loss_now, loss_new, 100.0 * math.sqrt(float(loss_now.mean())),
            100.0 * math.sqrt(float(loss_new.mean())))


def _judged(loss_now: np.ndarray, loss_new: np.ndarray, current_pct: float,
            candidate_pct: float, span: float, what: str) -> Comparison:
    n = len(loss_now)
    difference = loss_now - loss_new
    margin = SIGNIFICANCE * float(difference.std(ddof=1)) / math.sqrt(n)
    significant = float(difference.mean()) > margin
    large_enough = candidate_pct <= (1.0 - MIN_GAIN) * current_pct
    stretches = sorted(float(part.mean()) for part in np.array_split(difference, TIME_STRETCHES))
    steady = sum(stretches[:TIME_STRETCHES - FAVOURED_STRETCHES]) > 0.0
    better = significant and large_enough and steady
    if better:
        verdict = 'better'
    elif significant and large_enough:
        verdict = (f'better only in some stretches of time (without the {FAVOURED_STRETCHES} '
                   f'of {TIME_STRETCHES} most in its favour it is not: a disturbance for a '
                   'while, not the calibration)')
    else:
        verdict = 'not better beyond noise'
    return Comparison(better, current_pct, candidate_pct, n, span,
                      f'{verdict} on {n} {what}: residual {current_pct:.2f} % -> '
                      f'{candidate_pct:.2f} %')


# --- does the calibration in force still fit? ------------------------------------------------

MISFIT_WINDOW_S = 10.0
"""Recent evidence judged: the last 10 s of the stream."""

MISFIT_CONFIRM_S = 3.0
"""The verdict 'off' must hold for 3 s of stream before it is reported."""

MISFIT_MIN_READINGS = 20
"""Recent held-out readings needed before the calibration in force is judged at all."""

MISFIT_MIN_SPAN = 0.15
"""The recent evidence must span 15 % of the directions (12 of 80 cells: a few seconds of turning)
and lie on a shell: a still sensor next to a passing magnet traces no sphere."""

MISFIT_FACTOR = 3.0
"""'Clearly off': the median error is over three times what the calibration's own residual
predicts (median |e| of noise alone is about 0.67 of its RMS)..."""

MISFIT_FLOOR = 0.5
"""...and over half the residual gate: the median |e| of a calibration whose offset is off by a
tenth of the field is about 5 %. A median is unmoved by a disturbance that lasts less than half
the window..."""

MISFIT_EXPLAINED = 3.0
"""...and over three times what remains once the corrected readings are re-centred on their own
sphere: a calibration that no longer fits leaves errors a new offset explains (another board's
file: 230 % -> 0.4 %), a field disturbed from moment to moment does not (a disturbed recording:
7.8 % -> 4.5 %)."""


@dataclass(frozen=True)
class FitCheck:
    """The calibration in force judged on recent evidence."""

    judged: bool
    off: bool
    median_error_pct: float
    measured_field: float
    expected_field: float
    span: float
    explained_pct: float = math.nan
    """The median error left once the corrected readings are re-centred on their own sphere."""


def check_fit(calibration: Calibration, recent: np.ndarray, gate_pct: float) -> FitCheck:
    """Judge ``calibration`` on ``recent`` held-out readings (see the MISFIT_* constants)."""
    expected = calibration.field_strength
    span = evidence_span(recent, MISFIT_MIN_READINGS)
    if span < MISFIT_MIN_SPAN:
        return FitCheck(False, False, math.nan, math.nan, expected, span)
    errors = relative_errors(calibration, recent)
    median_error = float(np.median(np.abs(errors)))
    own = (calibration.metadata_number('residual_rms_pct') or 0.0) / 100.0
    threshold = max(MISFIT_FLOOR * gate_pct / 100.0, MISFIT_FACTOR * 0.67 * own)
    explained = _sphere_error(calibration.apply(recent))
    off = median_error > threshold and median_error > MISFIT_EXPLAINED * explained
    return FitCheck(True, off, 100.0 * median_error, expected * float(1.0 + np.median(errors)),
                    expected, span, 100.0 * explained)


def _sphere_error(points: np.ndarray) -> float:
    """Median relative distance from the least-squares sphere through ``points`` (inf when
    they determine none)."""
    scale = float(np.abs(points).max())
    if not scale > 0.0:
        return math.inf
    unit = points / scale
    design = np.column_stack([2.0 * unit, np.ones(len(unit))])
    solution, *_ = np.linalg.lstsq(design, np.einsum('ij,ij->i', unit, unit), rcond=None)
    squared = float(solution[3] + solution[:3] @ solution[:3])
    if not (squared > 0.0 and math.isfinite(squared)):
        return math.inf
    radius = math.sqrt(squared)
    return float(np.median(np.abs(np.linalg.norm(unit - solution[:3], axis=1) / radius - 1.0)))


class MisfitMonitor:
    """Turns a series of FitChecks into a confirmed misfit, and back once it fits again: each
    verdict must hold for MISFIT_CONFIRM_S of judged checks before it changes the state.

    A misfit is the world's (``world``: a magnet, steel, a vehicle in the room) when, within
    MISFIT_WINDOW_S before it is confirmed, the gyroscope's turning said the sensor still has the
    offset in force while the field it turns changed (``verdicts.world_disturbance``, told by
    ``offset_looked``) and no later look found the offset moved: the calibration stays, and
    ``world_since`` says from when the readings are the disturbance's, not the sensor's (kept
    once it cleared, for the session to forget them; None after a misfit of the sensor)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.misfit = False
        self.world = False
        self.world_since: float | None = None
        self.last: FitCheck | None = None
        self._since: float | None = None  # start of the run of checks that disagree
        self._error = 0.0  # the latest judged check's median |B| error, field units
        self._world_look: float | None = None  # the latest look that saw the world change
        self._moved_look: float | None = None  # the latest look that saw the offset move

    def offset_looked(self, now_s: float, world: bool, moved: bool) -> None:
        """A gyro look at the offset (``step``): it saw the world's field change around an
        unchanged offset (``world``), or the offset move (``moved``), or neither."""
        if world:
            self._world_look = now_s
        if moved:
            self._moved_look = now_s

    @property
    def uncertainty(self) -> float:
        """While a misfit is confirmed, the median |B| error of the latest judged check in field
        units (what each corrected component may be off by); 0.0 while the calibration fits."""
        return self._error if self.misfit else 0.0

    def update(self, now_s: float, check: FitCheck) -> str | None:
        """'confirmed' (or 'world', the world's) or 'cleared' when the state changes, else
        None."""
        self.last = check
        if not check.judged:
            return None
        self._error = check.median_error_pct / 100.0 * check.expected_field
        if check.off == self.misfit:
            self._since = None
            return None
        if self._since is None:
            self._since = now_s
        if now_s - self._since < MISFIT_CONFIRM_S:
            return None
        onset, self.misfit, self._since = self._since, check.off, None
        if not self.misfit:
            self.world = False
            return 'cleared'
        look, moved = self._world_look, self._moved_look
        self.world = (look is not None and now_s - look <= MISFIT_WINDOW_S
                      and (moved is None or moved < look))
        self.world_since = min(onset, look) - MISFIT_WINDOW_S / 2.0 if self.world else None
        return 'world' if self.world else 'confirmed'


__all__ = [
    'HOLD_OUT_EVERY',
    'MIN_EVIDENCE',
    'Comparison',
    'FitCheck',
    'HeldOutEvidence',
    'MisfitMonitor',
    'check_fit',
    'compare_on_evidence',
    'compare_residuals',
    'evidence_span',
    'magnitude_residual_pct',
    'relative_errors',
]
