# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Whether a finished fit changes the calibration in force, and what the log says about it.

One pure function per kind of fit: it takes the job's outcome, the calibration in force and the
few facts it needs, and returns a :class:`Verdict`; ``CalibrationSession._complete`` applies it
(through ``_put_in_force``) and does the bookkeeping. To change when a fit goes in force, change
the function here: :func:`automatic_verdict` for automatic calibration, :func:`refinement_verdict`
for refinement, :func:`request_verdict` for ``~/calibrate``, :func:`realign_verdict` for a new
rotation into the IMU frame, :func:`check_verdict` for misfit and online tracking and
:func:`gyro_verdict` for the first calibration from the gyroscope's turning and
:func:`step_verdict` for a hard-iron step it sees once calibrated.

One verdict has state, and so lives beside stream time rather than here:
``alignment_wait.AlignmentWait.judge`` takes :func:`automatic_verdict`'s verdict on the first
automatic calibration and holds it back (bounded) until it can be aligned to the IMU. It is the
only rule outside this file that changes what goes in force; the session applies its verdict
as it applies these. The compensation's verdict is :func:`compensation_verdict`, asked through
``CompensationLearner.judged`` (which keeps the fit for reports).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.fit.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.fit.compensation import interference_pct
from mag_calibrator_ros.calibration.fit.coverage import CELL_COUNT
from mag_calibrator_ros.calibration.fit.earth_field import EarthField, disturbance_text
from mag_calibrator_ros.calibration.fit.gyro_aided import GyroAidedFit
from mag_calibrator_ros.calibration.live.evidence import MIN_EVIDENCE, Comparison, FitCheck
from mag_calibrator_ros.calibration.live.jobs import JobOutcome
from mag_calibrator_ros.calibration.live.report import (
    CalibrationAttempt,
    calibration_summary,
    coverage_pct,
    format_field,
    interference_text,
    misfit_text,
    reference_text,
    world_text,
)
from mag_calibrator_ros.calibration.live.settings import SessionSettings

COVERAGE_SLACK = 2.0 / CELL_COUNT
"""A candidate may cover up to two of the 80 direction cells fewer than the calibration in
force: which cells a buffer of 100 points reaches changes by a cell or two as its points are
replaced, and a candidate better beyond noise on held-out readings was refused for that alone
(bno055 replayed with fresh noise: 2.12 % -> 2.04 % on 830 held-out readings, then never
refined again). More than that is a narrower buffer, and stays refused."""


@dataclass(frozen=True)
class Verdict:
    """What to do with a finished fit: put a calibration in force or not, and what to log."""

    adopt: Calibration | None = None
    """The calibration to put in force; None keeps the one in force."""
    source: str = ''
    """Why it goes in force: 'request', 'auto', 'refine', 'realign' or 'tracking'."""
    level: str = 'info'
    message: str = ''
    """The event to log ('info', 'warning' or 'debug'); no event when empty."""
    attempt: CalibrationAttempt | None = None
    """The fit phrased for a service answer and /diagnostics' last_calibrate; None leaves the
    previous one."""
    collect_anew: bool = False
    """A check confirmed a misfit and auto_calibrate is on: forget the samples from before it."""


def request_verdict(outcome: JobOutcome, current: Calibration | None, units: str,
                    earth: EarthField | None) -> Verdict:
    """``~/calibrate``: a fit that passes its gates goes in force, whatever is in force now."""
    result = outcome.result
    kept = ('; the previous calibration stays in force' if current is not None
            else '; still uncalibrated')
    if outcome.error or result is None:
        attempt = CalibrationAttempt(False, f'calibration failed: {outcome.error}{kept}', outcome)
    elif result.success:
        message = calibration_summary(result.calibration, units, earth)
        comparison = outcome.comparison
        if comparison is not None and comparison.readings >= MIN_EVIDENCE:
            message += (f'; on held-out readings {comparison.current_pct:.2f} % before, '
                        f'{comparison.candidate_pct:.2f} % now')
        message += reference_text(outcome, earth)
        attempt = CalibrationAttempt(True, message, outcome)
        return Verdict(result.calibration, 'request', 'info', f'calibrated: {message}', attempt)
    else:
        attempt = CalibrationAttempt(
            False, f'calibration failed: {result.reason}{kept}{reference_text(outcome, earth)}',
            outcome)
    return Verdict(level='warning', message=attempt.message, attempt=attempt)


def automatic_verdict(outcome: JobOutcome, current: Calibration | None, misfit: bool,
                      units: str, earth: EarthField | None) -> Verdict:
    """An automatic fit goes in force only when all of these hold:

    - it ran without error on a ready buffer: direction coverage at least ``min_coverage``, or
      the whole heading circle for yaw-only data (``jobs.readiness``; else there is no result);
    - it passed every gate of the fit (``fitting``): at least ``min_samples``, coverage at least
      ``min_coverage``, residual at most ``max_residual_pct``, condition number at most
      ``max_condition``, soft-iron axis ratio at most ``max_axis_ratio``; with
      ``earth_field_gate``, also the World Magnetic Model's (field within
      ``max_field_error_pct``, dip within ``max_dip_error_deg``);
    - nothing is in force, or what is in force is a confirmed misfit (``evidence.MisfitMonitor``):
      any other calibration in force is replaced only by refinement (``refinement_verdict``).
    """
    if outcome.error:
        return Verdict(level='warning', message=f'automatic calibration failed: {outcome.error}')
    result = outcome.result
    if result is None:  # not ready: coverage below what the automatic gate needs
        coverage = outcome.coverage
        shown = '?' if coverage is None else f'{100.0 * coverage.fraction:.0f} %'
        return Verdict(level='debug', message=f'automatic calibration not tried yet: '
                       f'coverage {shown} is not enough')
    if not result.success:
        return Verdict(level='info', message=f'automatic calibration not yet: {result.reason}',
                       attempt=CalibrationAttempt(False, f'calibration failed: {result.reason}',
                                                  outcome))
    if current is not None and not misfit:
        return Verdict()  # calibrated meanwhile (a request or a file): refinement takes over
    attempt = CalibrationAttempt(True, calibration_summary(result.calibration, units, earth)
                                 + reference_text(outcome, earth), outcome)
    what = 'recalibrated automatically' if current is not None else 'calibrated automatically'
    return Verdict(result.calibration, 'auto', 'info', f'{what}: {attempt.message}', attempt)


def gyro_verdict(outcome: JobOutcome, current: Calibration | None, units: str) -> Verdict:
    """The first calibration from the gyroscope's turning (``jobs.gyro_aided_outcome``), while
    nothing is in force. The raw field is a candidate like any other, so that a sensor that
    arrives calibrated is never made worse:

    - the fit (the offset, or the soft iron with it) goes in force when it passed its own bounds
      (``fit_gyro_aided``: directions determined to MAX_DIRECTION_STD_DEG, the turned readings
      within the residual gate) and beats the raw field on the held-out windows by the rule
      every candidate meets (``evidence.compare_residuals``);
    - else, when it passed its bounds and the raw field's own turned readings are within the
      residual gate, the raw field goes in force: the gyroscope confirmed it;
    - else nothing: the sphere fits (``automatic_verdict``) go on as before.
    The sphere's refinements then judge whatever went in force on held-out readings; while
    a gyro fit is in force, ``gyro_refinement_verdict`` judges the next ones."""
    if outcome.error:
        return Verdict(level='warning', message=f'gyro-aided calibration failed: {outcome.error}')
    fit, comparison = outcome.gyro_fit, outcome.comparison
    if current is not None:
        return gyro_refinement_verdict(outcome, current, units)
    if fit is None or not fit.success or comparison is None:
        reason = fit.reason if fit is not None and fit.reason else 'no offset solved'
        return Verdict(level='debug', message=f'gyro-aided calibration not yet: {reason}')
    uncertain = format_field(float(np.max(fit.offset_std)), units)
    if comparison.better:
        candidate = fit.calibration.with_metadata(residual_rms_pct=round(fit.residual_pct, 3))
        attempt = CalibrationAttempt(True, calibration_summary(candidate, units), outcome)
        return Verdict(candidate, 'gyro', 'info',
                       f"calibrated from the gyroscope's turning ({fit.windows} windows, "
                       f'directions uncertain by {fit.direction_std_deg:.2f} deg, the offset by '
                       f'{uncertain}): {comparison.reason}; {attempt.message}',
                       attempt)
    if fit.raw_residual_pct <= outcome.job.options.max_residual_pct:
        radius = float(np.median(np.linalg.norm(outcome.job.turned.readings, axis=1)))
        kept = {key: value for key, value in fit.calibration.metadata.items()
                if key not in ('direction_std_deg', 'rotation_deg')}  # the fit's, not the raw's
        raw = Calibration(np.zeros(3), np.eye(3), radius, 'sphere', {
            **kept, 'confirmed': 'raw', 'residual_rms_pct': round(fit.raw_residual_pct, 3)})
        attempt = CalibrationAttempt(True, calibration_summary(raw, units), outcome)
        offset = format_field(float(np.linalg.norm(fit.calibration.offset)), units)
        return Verdict(raw, 'gyro', 'info',
                       f"the sensor's own calibration holds: the gyroscope's turning finds an "
                       f'offset of {offset} (uncertain by {uncertain}), {comparison.reason}',
                       attempt)
    return Verdict(level='debug', message=f'gyro-aided calibration not yet: {comparison.reason}; '
                   f'the raw field spreads by {fit.raw_residual_pct:.1f} %')


def gyro_improvable(calibration: Calibration | None, disturbed: bool = False) -> bool:
    """Whether the calibration in force is a gyro fit (its directions' sigma known) that a
    fit of more turning may improve on; a sphere fit, a file or the raw field confirmed are
    the sphere refinements' to judge, and in a disturbance of the world (``disturbed``)
    nothing is learned."""
    return (not disturbed and calibration is not None
            and calibration.metadata.get('fit') == 'gyro_aided'
            and calibration.metadata_number('direction_std_deg') is not None)


def gyro_refinement_verdict(outcome: JobOutcome, current: Calibration, units: str) -> Verdict:
    """A gyro fit of the latest turning replaces the gyro fit in force when the calibration
    in force is still that one (``gyro_improvable``), the new fit passed its own bounds, its
    directions are surer than the one in force's, and it beats it on the held-out windows by
    the rule every candidate meets: a first fit from a few seconds of turning (a magnet just
    attached) improves as the turning grows, never worse on what was held out."""
    fit, comparison = outcome.gyro_fit, outcome.comparison
    if (current is not outcome.job.current or not gyro_improvable(current) or fit is None
            or not fit.success or comparison is None):
        return Verdict()
    before = current.metadata_number('direction_std_deg')
    if not (fit.direction_std_deg < before and comparison.better):
        return Verdict(level='debug', message=f'gyro-aided refinement not adopted: directions '
                       f'uncertain by {fit.direction_std_deg:.2f} deg (in force {before:.2f}), '
                       f'{comparison.reason}')
    candidate = fit.calibration.with_metadata(residual_rms_pct=round(fit.residual_pct, 3))
    attempt = CalibrationAttempt(True, calibration_summary(candidate, units), outcome)
    return Verdict(candidate, 'gyro', 'info',
                   f"refined from the gyroscope's turning ({fit.windows} windows, directions "
                   f'uncertain by {before:.2f} -> {fit.direction_std_deg:.2f} deg): '
                   f'{comparison.reason}', attempt)


STEP_SIGMAS = 5.0
"""A step must move the offset by five of its own standard deviations (each reading of a look
every second is judged: a one-in-a-million chance of a false step a look)..."""

MIN_STEP = 0.05
"""...and by 5 % of the field at least (a heading error of up to 3 degrees): smaller changes are
the refinements' to find, from the sphere."""


EQUIVALENT_SIGMAS = 3.0
"""A look says the offset in force still holds when the offset it fitted, widened by three of its
standard deviations, stays within MIN_STEP of the field of it: a step the looks would call one
is ruled out, not merely unproven."""


def offset_look(outcome: JobOutcome, current: Calibration | None) -> tuple[bool, bool]:
    """What a step look (``jobs.step_outcome``) says of the sensor: (world, moved).

    ``world``: the offset in force still holds (EQUIVALENT_SIGMAS) while the field its readings
    turn is another strength, by MIN_STEP of it at least: the field changed around the sensor
    (a magnet, steel, a vehicle in the room), not on it; a body-fixed step moves the offset the
    turning sees, a world-fixed field turns with the world and leaves it. ``moved``: the
    offset moved by a step (STEP_SIGMAS and MIN_STEP). Neither when the look saw too little."""
    fit = outcome.gyro_fit
    if outcome.error or current is None or fit is None or not fit.success:
        return False, False
    size, sigma = _offset_change(fit, current)
    held = size + EQUIVALENT_SIGMAS * sigma < MIN_STEP * current.field_radius()
    changed = abs(outcome.field_seen / current.field_strength - 1.0) > MIN_STEP
    return held and changed, _is_step(size, sigma, current)


def _offset_change(fit: GyroAidedFit, current: Calibration) -> tuple[float, float]:
    """How far a look's offset lies from the one in force, and that distance's 1-sigma."""
    return (float(np.linalg.norm(fit.calibration.offset - current.offset)),
            float(np.linalg.norm(fit.offset_std)))


def _is_step(size: float, sigma: float, current: Calibration) -> bool:
    """STEP_SIGMAS of its own uncertainty and MIN_STEP of the field: a step."""
    return size >= STEP_SIGMAS * sigma and size >= MIN_STEP * current.field_radius()


def step_verdict(outcome: JobOutcome, current: Calibration | None, units: str,
                 disturbed: bool = False) -> Verdict:
    """A hard-iron step (``jobs.step_outcome``): the latest turned readings agree with another
    offset, the rest of the calibration in force kept. It goes in force at once, and what was
    learned before it is forgotten (``collect_anew``: the old buffer is not mixed with the new
    sensor), when the offset passed its own bounds, moved by STEP_SIGMAS of its uncertainty and
    MIN_STEP of the field, and beats the calibration in force on the held-out windows by the
    rule every candidate meets. A field disturbed in the world (a magnet in the room) agrees
    with no offset as the sensor turns: no step; while one is known (``disturbed``: the
    misfit is the world's) the readings are the disturbance's and no step is taken from them.
    Looks that find none say nothing."""
    fit, comparison = outcome.gyro_fit, outcome.comparison
    if outcome.error or current is None or current is not outcome.job.current or disturbed:
        return Verdict()
    if fit is None or not fit.success or comparison is None or not comparison.better:
        return Verdict()
    size, sigma = _offset_change(fit, current)
    if not _is_step(size, sigma, current):
        return Verdict()
    candidate = fit.calibration
    attempt = CalibrationAttempt(True, calibration_summary(candidate, units), outcome)
    return Verdict(candidate, 'step', 'warning',
                   f'hard-iron step: the offset moved by {format_field(size, units)} (uncertain '
                   f'by {format_field(sigma, units)}): a magnet, a battery or a tool mounted '
                   f"near the sensor? Re-learned from the gyroscope's turning: "
                   f'{comparison.reason}; collecting anew', attempt, collect_anew=True)


MAX_REFINED_FIELD_STEP = 0.05
MAX_REFINED_FIELD_CHANGE = 0.10
"""A refinement moves F by at most 5 % of the one in force, and a chain of them by at most 10 %
of the F it started from (``CHAIN_KEY``, unit-free: the chain's F over its first). On a ground
robot the offset along the turning axis is barely observed, and a sphere centred farther along
it, with a larger F, makes every horizontal error a smaller share of F: each such fit won on
held-out readings, and a chain walked F from 54 to 344 µT (issue #47). A true F that far off is
a new calibration's to find (a misfit)."""
CHAIN_KEY = 'refined_field_ratio'


def chain_ratio(current: Calibration, candidate: Calibration) -> float:
    """The candidate's F over the F its chain of refinements started from."""
    return (current.metadata_number(CHAIN_KEY) or 1.0) * (candidate.field_strength
                                                          / current.field_strength)


def field_walk(current: Calibration, candidate: Calibration) -> str | None:
    """Why ``candidate`` moves F further than refinement may (MAX_REFINED_FIELD_*), or None.
    Only between planar calibrations, once the one in force determined its offset along the
    normal (``levelled_offset_normal_std``): a first one from a level turn knows nothing there,
    and a 3-D fit observes it (its coverage gates)."""
    if not (current.model == candidate.model == 'planar'
            and current.metadata_number('levelled_offset_normal_std') is not None):
        return None
    step = candidate.field_strength / current.field_strength - 1.0
    total = chain_ratio(current, candidate) - 1.0
    if abs(step) <= MAX_REFINED_FIELD_STEP and abs(total) <= MAX_REFINED_FIELD_CHANGE:
        return None
    return (f'it moves the field strength by {100 * step:+.1f} % ({100 * total:+.1f} % since '
            f'the fit refinements started from), beyond {100 * MAX_REFINED_FIELD_STEP:g} % '
            f'({100 * MAX_REFINED_FIELD_CHANGE:g} %): a term the readings barely observe')


def refinement_verdict(outcome: JobOutcome, current: Calibration | None) -> Verdict:
    """The adoption rule of refinement: a fit of the buffer goes in force when all of these hold,
    and each one that fails is the reason logged (debug) for keeping the calibration in force:

    - it passed its gates (``fitting``): it is what ``~/calibrate`` would put in force now;
    - it is better than the calibration it was judged against on held-out readings no fit has
      seen (``evidence.compare_on_evidence``): at least MIN_EVIDENCE of them spanning
      MIN_EVIDENCE_SPAN of the directions, a capped residual lower by SIGNIFICANCE standard
      errors and by MIN_GAIN, and still lower without the stretches of time most in its favour
      (a magnet that stayed a while is not an improvement);
    - that calibration is still in force, and the fit covers no fewer directions
      (``coverage_kept``);
    - with the gyroscope, the one in force is not better than it on the readings the gyroscope
      turned (``outcome.turning``): magnitudes cannot see a soft iron that bends directions, the
      turning can;
    - it moves F no further than MAX_REFINED_FIELD_STEP, and the chain no further than
      MAX_REFINED_FIELD_CHANGE (``field_walk``): the rule cannot be won by scaling F.

    It converges: the held-out store keeps up to READINGS_PER_CELL a direction cell, so a real
    gain of a few per cent is proven once the sensor has turned long enough, and the calibration
    in force ends as good as what ``~/calibrate`` gives (benchmarks/bench_replay.py); what is
    left meanwhile is reported as ``could_be_better`` (report.could_be_better)."""
    result, comparison = outcome.result, outcome.comparison
    if outcome.error:
        return Verdict(level='warning', message=f'refinement failed: {outcome.error}')
    turning = outcome.turning
    if (comparison is not None and comparison.better and turning is not None
            and turning.better):
        return Verdict(level='debug', message='refinement kept the calibration: it fits the '
                       f'magnitudes better ({comparison.reason}) but turns directions worse: the '
                       f'one in force is {turning.reason}')
    walk = (None if result is None or not result.success or current is None
            else field_walk(current, result.calibration))
    if walk is not None and comparison is not None and comparison.better:
        return Verdict(level='debug', message=f'refinement kept the calibration: {walk}, '
                       f'though {comparison.reason}')
    if (result is not None and result.success and comparison is not None
            and comparison.better and current is outcome.job.current
            and coverage_kept(current, result.calibration)):
        candidate = result.calibration.with_metadata(**{
            CHAIN_KEY: round(chain_ratio(current, result.calibration), 6)})
        return Verdict(candidate, 'refine', 'info',
                       f'refined: residual {comparison.current_pct:.2f} % -> '
                       f'{comparison.candidate_pct:.2f} % on {comparison.readings} '
                       f'held-out readings, coverage {coverage_pct(current)} -> '
                       f'{coverage_pct(candidate)} ({candidate.model})')
    if comparison is not None and comparison.better and current is outcome.job.current:
        return Verdict(level='debug', message=f'refinement kept the calibration: the fit '
                       f'covers fewer directions ({coverage_pct(current)} -> '
                       f'{coverage_pct(result.calibration)}), though {comparison.reason}')
    if comparison is not None:
        return Verdict(level='debug',
                       message=f'refinement kept the calibration: {comparison.reason}')
    if result is not None and not result.success:
        return Verdict(level='debug', message=f'refinement kept the calibration: the fit '
                       f'failed its gates: {result.reason}')
    return Verdict()


def judged_on_evidence(comparison: Comparison | None) -> bool:
    """A refinement's comparison rested on enough held-out readings to say something (the
    scheduler slows refinement down once such comparisons stop finding anything better)."""
    return comparison is not None and math.isfinite(comparison.current_pct) and (
        comparison.readings >= MIN_EVIDENCE)


def realign_verdict(outcome: JobOutcome, current: Calibration | None) -> Verdict:
    """A refinement not adopted may still align better: its rotation goes in force when the fit
    passed its own gates against the calibration still in force, and that one has no rotation
    yet or the new one differs by more than its uncertainty."""
    alignment = outcome.alignment
    if (current is None or current is not outcome.job.current or not passed_own_gates(outcome)
            or alignment is None or not alignment.success):
        return Verdict()
    change = rotation_angle_deg(alignment.rotation @ current.rotation.T)
    if current.aligned and change <= max(3.0 * alignment.rotation_std_deg, 0.05):
        return Verdict()
    return Verdict(current.with_rotation(alignment.rotation, **alignment.metadata()), 'realign',
                   'info', f'{alignment.summary()} (changed by {change:.2f} deg)')


def check_verdict(outcome: JobOutcome, current: Calibration | None, misfit_change: str | None,
                  since_last_check_s: float | None, settings: SessionSettings,
                  units: str, disturbed: bool = False, silence: str = '') -> Verdict:
    """A check of the calibration in force on recent held-out readings.

    ``misfit_change``: what ``MisfitMonitor.update`` made of it ('confirmed', 'world' (a
    disturbance of the world: the calibration stays and nothing is learned), 'cleared' or
    None); ``disturbed``: the world's misfit holds, no tracking step; ``silence``: the own-field
    inputs held at a stale value (``CompensationLearner.silence_note``), said with a misfit as
    a cause as likely as the one named. With online tracking, a
    step towards the tracker's calibration goes in force when the
    tracker beats the calibration in force by ``tracking_improvement`` on held-out readings; the
    step is bounded by ``tracking_max_change_rate`` times the stream seconds since the previous
    check (``since_last_check_s``, None for the first), so it can never jump.
    """
    if outcome.error:
        return Verdict(level='warning',
                       message=f'checking the calibration failed: {outcome.error}')
    if current is None or outcome.job.current is not current:
        return Verdict()  # judged a calibration no longer in force
    level, message, collect_anew = 'debug', check_text(outcome.fit_check), False
    if misfit_change == 'confirmed':
        level, message = 'warning', misfit_text(outcome.fit_check, units, settings.auto_calibrate)
        collect_anew = settings.auto_calibrate
    elif misfit_change == 'world':  # the sensor is as calibrated: nothing to collect anew
        level, message = 'warning', world_text(outcome.fit_check, units)
    if silence and misfit_change in ('confirmed', 'world'):
        message += f'; {silence}'
    elif misfit_change == 'cleared':
        level, message = 'info', (f'the calibration in force fits the live data again (median '
                   f'error {outcome.fit_check.median_error_pct:.1f} %)')
    step = None
    comparison = outcome.comparison
    if (comparison is not None and not disturbed and since_last_check_s is not None
            and since_last_check_s > 0
            and comparison.better and comparison.candidate_pct
            < settings.tracking_improvement * comparison.current_pct):
        try:
            step = bounded_step(current, outcome.job.tracked,
                                settings.tracking_max_change_rate * since_last_check_s)
        except CalibrationError:
            step = None
    return Verdict(step, 'tracking' if step is not None else '', level, message,
                   collect_anew=collect_anew)


def check_text(check: FitCheck | None) -> str:
    """One debug line per check of the calibration in force: judged or why not."""
    if check is None:
        return ''
    if not check.judged:
        return (f'calibration in force not judged: the recent held-out readings span '
                f'{100.0 * check.span:.0f} % of the directions')
    return (f'calibration in force judged on recent held-out readings: median error '
            f'{check.median_error_pct:.2f} % ({"off" if check.off else "fits"})')


def coverage_kept(current: Calibration, candidate: Calibration) -> bool:
    """A candidate may not cover less than the calibration in force: no fewer directions (by
    more than COVERAGE_SLACK), and never a planar fit in place of a 3-D one (a 3-D fit in place
    of a planar one is an upgrade)."""
    if candidate.model == 'planar' and current.model != 'planar':
        return current.model == 'identity'
    if current.model == 'planar' and candidate.model != 'planar':
        return True
    before, after = (c.metadata_number('coverage') for c in (current, candidate))
    if before is None:
        return True
    return after is not None and after >= before - COVERAGE_SLACK - 1e-9


def bounded_step(current: Calibration, target: Calibration, max_change: float) -> Calibration:
    """Move from ``current`` towards ``target`` by at most ``max_change`` (relative units).

    The offset moves at most ``max_change * F`` and the matrix at most ``max_change`` times its own
    norm, so a tracked calibration can never jump, however wrong the tracker is for a moment.
    """
    offset_delta = target.offset - current.offset
    matrix_delta = target.matrix - current.matrix
    offset_limit = max_change * current.field_strength
    matrix_limit = max_change * np.linalg.norm(current.matrix) / math.sqrt(3.0)
    offset_norm = float(np.linalg.norm(offset_delta))
    matrix_norm = float(np.linalg.norm(matrix_delta))
    fraction = 1.0
    if offset_norm > offset_limit:
        fraction = min(fraction, offset_limit / offset_norm)
    if matrix_norm > matrix_limit:
        fraction = min(fraction, matrix_limit / matrix_norm)
    return Calibration(
        current.offset + fraction * offset_delta,
        current.matrix + fraction * matrix_delta,
        current.field_strength,
        current.model,
        {**current.metadata, 'source': 'online_tracking'},
        current.rotation,
    )


def passed_own_gates(outcome: JobOutcome) -> bool:
    """The fit passed its gates, or failed only the World Magnetic Model's."""
    result, check = outcome.result, outcome.earth_check
    if result is None or outcome.error:
        return False
    return result.success or (check is not None and result.reason == disturbance_text(check))


def compensation_verdict(outcome: JobOutcome, current: Calibration | None) -> Verdict:
    """A learned compensation (``K``, ``c``: the robot's own field) goes in force only when
    all hold: the fit kept terms (each determined by its input's variation and significant,
    ``fit/compensation.py``), the calibration it was learned on is still in force, and it is
    better on held-out readings with their inputs by refinement's rule
    (``evidence.compare_on_evidence``). Otherwise nothing changes and the log says (debug)
    what kept it, with what motion would determine a term."""
    fit = outcome.compensation
    if outcome.error or fit is None:
        return Verdict(level='warning',
                       message=f'compensation fit failed: {outcome.error or "no result"}')
    if fit.calibration is None:
        return Verdict(level='debug', message=f'compensation not learned: {fit.reason}')
    if current is None or current is not outcome.job.current:
        return Verdict()  # another calibration went in force meanwhile: learn on it next
    comparison = outcome.comparison
    if comparison is None or not comparison.better:
        why = 'no held-out readings' if comparison is None else comparison.reason
        return Verdict(level='debug', message=f'compensation kept as it is: {why}')
    compensation = fit.calibration.compensation
    interference = interference_pct(fit.terms, fit.kept)
    learned = {'compensation_removed_pct': round(fit.removed_pct, 3),
               'compensation_readings': fit.readings}
    if interference is not None:
        learned['compensation_interference_pct'] = round(interference, 2)
    candidate = fit.calibration.with_metadata(**learned)
    terms = ', '.join(f'{term.name} {term.effect_pct:.2f} % of the field' for term in fit.terms
                      if term.name in fit.kept)
    t0 = ('' if compensation.reference_temperature is None
          else f', T0 {compensation.reference_temperature:g} degC')
    return Verdict(candidate, 'compensation', 'info', (
        f"compensating the robot's own field: {terms}{t0}; it removes {fit.removed_pct:.2f} % "
        f'of the field{interference_text(interference)}; {comparison.reason}'))


__all__ = [
    'COVERAGE_SLACK',
    'Verdict',
    'EQUIVALENT_SIGMAS',
    'MAX_REFINED_FIELD_CHANGE',
    'MAX_REFINED_FIELD_STEP',
    'CHAIN_KEY',
    'chain_ratio',
    'field_walk',
    'compensation_verdict',
    'automatic_verdict',
    'bounded_step',
    'check_text',
    'check_verdict',
    'coverage_kept',
    'gyro_improvable',
    'gyro_refinement_verdict',
    'gyro_verdict',
    'judged_on_evidence',
    'offset_look',
    'passed_own_gates',
    'realign_verdict',
    'refinement_verdict',
    'request_verdict',
    'step_verdict',
]
