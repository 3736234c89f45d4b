"""The session's state in words and numbers for people: log lines, service answers, /diagnostics.

Nothing here decides anything; every text a user reads about a calibration is built here, so a
wording is changed in one place (tests and users match on these texts: change them with care).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

from mag_calibrator_ros.calibration.fit.alignment import (
    Alignment,
    StaticAttitudes,
    rotation_angle_deg,
)
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS, Coverage
from mag_calibrator_ros.calibration.fit.earth_field import EarthField, EarthReference
from mag_calibrator_ros.calibration.fit.heading import COMPLETE_HEADING_COVERAGE
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.evidence import (
    MIN_GAIN,
    MISFIT_WINDOW_S,
    FitCheck,
    HeldOutEvidence,
    MisfitMonitor,
)
from mag_calibrator_ros.calibration.live.findings import Findings
from mag_calibrator_ros.calibration.live.jobs import JobOutcome
from mag_calibrator_ros.calibration.live.pairing import ImuPairing, RateMeter
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.live.tracker import OnlineTracker
from mag_calibrator_ros.calibration.live.worker import FitRunner

TESLA_TO_MICROTESLA = 1e6

Level = Literal['OK', 'WARN', 'ERROR']


@dataclass(frozen=True)
class CalibrationAttempt:
    """The outcome of one fit, phrased for a service answer or a log line."""

    success: bool
    message: str
    outcome: JobOutcome | None = None


def display_units(units: str) -> str:
    return 'uT' if units == 'T' else units


def format_field(value: float, units: str, unit: bool = True) -> str:
    """A field value for people: microtesla for tesla input, else as given."""
    text = f'{value * TESLA_TO_MICROTESLA:.2f}' if units == 'T' else f'{value:.6g}'
    return f'{text} {display_units(units)}' if unit else text


def calibration_summary(calibration: Calibration, units: str = 'T') -> str:
    """One line: model, offset, residual % and coverage % (when the fit recorded them)."""
    offset = ', '.join(format_field(v, units, unit=False) for v in calibration.offset)
    text = f'model {calibration.model}, offset [{offset}] {display_units(units)}'
    residual, coverage, samples = (calibration.metadata_number(key)
                                   for key in ('residual_rms_pct', 'coverage', 'samples'))
    if residual is not None:
        text += f', residual {residual:.2f} %'
    if coverage is not None:
        text += f', coverage {100.0 * coverage:.0f} %'
    if samples is not None:
        text += f', {samples:.0f} samples'
    if calibration.metadata.get('levelled_by_gravity') is True:
        dip = calibration.metadata_number('levelled_dip_deg')
        text += ', levelled by gravity' + ('' if dip is None else f' (dip {dip:.1f} deg)')
    if calibration.aligned:
        text += f', rotated {rotation_angle_deg(calibration.rotation):.2f} deg into the IMU frame'
    return text + unobserved_text(calibration, units) + compensation_text(calibration, units)


def compensation_text(calibration: Calibration, units: str = 'T') -> str:
    """'; compensating the robot's own field: K ... per unit of <input>, c ... per degC around
    T0, removing x % of the field (learned <time>)' ('' without a compensation)."""
    compensation = calibration.compensation
    if compensation is None:
        return ''
    shown = display_units(units)
    parts = []
    for j, name in enumerate(compensation.inputs):
        if any(compensation.interference[:, j]):
            values = ', '.join(format_field(v, units, unit=False)
                               for v in compensation.interference[:, j])
            parts.append(f'[{values}] {shown} per unit of {name}')
    if any(compensation.temperature_coefficient):
        values = ', '.join(format_field(v, units, unit=False)
                           for v in compensation.temperature_coefficient)
        parts.append(f'[{values}] {shown}/degC around {compensation.reference_temperature:g} '
                     'degC')
    if not parts:
        return ''
    text = "; compensating the robot's own field: " + ', '.join(parts)
    removed = calibration.metadata_number('compensation_removed_pct')
    if removed is not None:
        text += f', {removed:.2f} % of the field'
    learned = calibration.metadata.get('compensation_time')
    return text + (f' (learned {learned})' if learned else '')


UNOBSERVED_WORDS = {'offset_normal': 'the offset along the turning axis',
                    'matrix_normal': 'the scale along it'}
"""The terms a fit reports unobserved (``FitMetrics.unobserved``), in a user's words."""


def unobserved_text(calibration: Calibration, units: str = 'T') -> str:
    """'; not observable turning in one plane, held (not fitted): ...' ('' when every term was
    fitted): a planar calibration's offset along the turning axis (unless tilts determined it)
    and its scale along it are held at the prior; without that offset (and unlevelled by
    gravity), F is the field in the turning plane (the horizontal field), not the total. A
    levelled fit whose small tilts told that offset only roughly says how roughly."""
    unobserved = calibration.metadata.get('unobserved')
    if not isinstance(unobserved, list | tuple) or not unobserved:
        return ''
    levelled = calibration.metadata.get('levelled_by_gravity') is True
    told = calibration.metadata_number('levelled_offset_normal_std') if levelled else None
    if told is not None and 0.0 < told and list(unobserved) == ['offset_normal', 'matrix_normal']:
        return ('; not observable turning in one plane, held (not fitted): the scale along the '
                "turning axis; the offset along it told by the floor's tilts only to "
                f'±{100.0 * told:.0f} % of the field')
    terms = ' and '.join(UNOBSERVED_WORDS.get(str(term), str(term)) for term in unobserved)
    if 'offset_normal' not in unobserved:  # 'it' would have nothing to point to
        terms = terms.replace('the scale along it', 'the scale along the turning axis')
    text = f'; not observable turning in one plane, held (not fitted): {terms}'
    if 'offset_normal' in unobserved and not levelled:
        text += (f'; F {format_field(calibration.field_strength, units)} is the field in that '
                 'plane, not the total')
    return text


NEEDS_TILTS = ('too few static attitudes', 'gravity directions too close',
               'rotation not determined')
"""Alignment failures whose remedy is more, more different tilts held still."""


def alignment_reason(alignment: Alignment, model: str) -> str:
    """Why an alignment was not applied, without advice to tilt a ``planar`` (yaw-only)
    calibration: a robot turning on the floor cannot, and its heading needs no tilts."""
    if model == 'planar' and alignment.reason.startswith(NEEDS_TILTS):
        return 'turning in place gives too few different tilts (the heading needs none)'
    return alignment.reason


def alignment_text(alignment: Alignment, model: str) -> str:
    """The alignment for a log line or an answer: '' when no still attitude was seen at all
    (nothing to say: every calibration without still tilts would carry it), and never advice
    to tilt a ``planar`` calibration (``alignment_reason``)."""
    if alignment.success:
        return alignment.summary()
    if alignment.attitudes == 0:
        return ''
    reason = alignment_reason(alignment, model)
    if reason != alignment.reason:
        return f'alignment to the IMU not determined: {reason}'
    return alignment.summary()


def coverage_pct(calibration: Calibration) -> str:
    """The coverage a calibration's fit recorded, '?' when it recorded none."""
    coverage = calibration.metadata_number('coverage')
    return '?' if coverage is None else f'{100.0 * coverage:.0f} %'


def reference_text(outcome: JobOutcome, earth: EarthField | None) -> str:
    """'; aligned to the IMU: ...; field 1.01x the model's ...' for an answer or a log."""
    text = ''
    result = outcome.result
    if outcome.alignment is not None:
        fitted = None if result is None else result.calibration
        alignment = alignment_text(outcome.alignment, '' if fitted is None else fitted.model)
        text += f'; {alignment}' if alignment else ''
    check = outcome.earth_check
    if check is not None:
        parts = []
        if check.radius_ratio is not None:
            parts.append(f"field {check.radius_ratio:.3f}x the model's")
        if check.dip_error_deg is not None:
            parts.append(f'dip {check.dip_error_deg:+.2f} deg against it')
        parts.append(f'declination {check.declination_deg:.2f} deg')
        text += f'; {earth.model if earth else "model"}: {", ".join(parts)}'
    return text


def misfit_text(check: FitCheck | None, units: str, auto_calibrate: bool) -> str:
    """Why the calibration in force does not fit, and what happens about it ('' unjudged)."""
    if check is None or not check.judged:
        return ''
    measured = format_field(check.measured_field, units)
    expected = format_field(check.expected_field, units)
    action = ('collecting to calibrate anew (auto_calibrate)' if auto_calibrate
              else 'call ~/reset then ~/calibrate, or set auto_calibrate')
    return (f'calibration does not fit the live data: |B| {measured} vs {expected} '
            f'expected (median error {check.median_error_pct:.1f} % over the last '
            f'{MISFIT_WINDOW_S:.0f} s, {100 * check.span:.0f} % of the directions) - other '
            f'sensor, new payload, or a magnet nearby? {action}')


NO_INPUT_GRACE_S = 3.0
"""No 'no input' line before this long (nor a progress period) without message or publisher:
discovering a driver that is already running takes a moment."""


def no_input_text(topic: str) -> str:
    return (f'no input on {topic}: is the driver running, in this namespace? '
            f'(ros2 topic info {topic})')


def no_message_text(topic: str, publishers: int, first: bool, waited_s: float,
                    period_s: float) -> str | None:
    """The progress line when no message came since the previous one (``first``: none ever):
    waiting while ``topic`` has publishers; 'no input' once ``waited_s`` since start-up reached
    a progress period and NO_INPUT_GRACE_S without either; None (nothing to say) before."""
    if publishers:
        return (f'waiting for {"the first" if first else "a"} message on {topic} '
                f'({publishers} publisher(s) found)')
    if waited_s < max(period_s, NO_INPUT_GRACE_S):
        return None
    return no_input_text(topic)


def progress_text(state: str, calibration: Calibration | None, coverage: Coverage,
                  buffer: SampleBuffer, settings: SessionSettings) -> str:
    """What to do next, e.g. 'coverage 63 % - keep rotating about the pitch axis (y)'."""
    fill = f'buffer {buffer.fill}/{buffer.capacity}'
    heading = coverage.cells == HEADING_SECTORS
    text = f'{"heading " if heading else ""}coverage {100.0 * coverage.fraction:.0f} %'
    if calibration is not None:
        return f'{state} ({calibration.model}); {text}, {fill}'
    needed = settings.min_coverage
    if heading and settings.auto_calibrate:
        needed = max(needed, COMPLETE_HEADING_COVERAGE)  # see jobs.readiness
    if coverage.fraction < needed:
        hint = coverage.hint or ('keep turning in place' if heading
                                 else 'keep rotating the sensor through every orientation')
        return f'{text} \u2014 {hint}; {fill}'
    if settings.auto_calibrate:
        return f'{text}, {fill} \u2014 enough to calibrate; calibrating automatically'
    return f'{text}, {fill} \u2014 enough to calibrate: call ~/calibrate'


def diagnostics_level(state: str, progress: str, input_rate_hz: float, no_input: str, *,
                      problem: str | None = None, refused: Mapping[str, int] | None = None,
                      misfit: str = '', earth_warning: str = '', alignment_warning: str = '',
                      imu_warning: str = '', input_problem: str = '') -> tuple[Level, str]:
    """The level and message of the calibrator's /diagnostics status: the first that applies of
    a problem of the node or its fit worker (ERROR), input no calibration can fix (wrong unit,
    normalised: ``sanity.py``), messages refused since the last report, a misfit, a disturbed
    field, a mounting error, an IMU that cannot be paired (WARN), calibrated (OK), no input,
    still calibrating (WARN)."""
    if problem is not None:
        return 'ERROR', problem
    if input_problem:
        return 'WARN', f'{state}: {input_problem}'
    if refused:
        counts = ', '.join(f'{reason} {count}' for reason, count in refused.items())
        return 'WARN', f'{state}: input messages refused since last report: {counts}'
    if state == 'calibrated-misfit':
        return 'WARN', misfit
    calibrated = state.startswith('calibrated')
    if calibrated and earth_warning:
        return 'WARN', f'{state}: {earth_warning}'
    if calibrated and alignment_warning:
        return 'WARN', f'{state}: {alignment_warning}'
    if imu_warning:
        return 'WARN', f'{state}: {imu_warning}'
    if calibrated:
        return 'OK', progress
    if input_rate_hz == 0.0:
        return 'WARN', f'{state}: {no_input}'
    return 'WARN', f'{state}: {progress}'


class ReportedSession(Protocol):
    """What /diagnostics reads of a ``CalibrationSession`` (which imports this module)."""

    settings: SessionSettings
    units: str
    calibration: Calibration | None
    buffer: SampleBuffer
    evidence: HeldOutEvidence
    misfit: MisfitMonitor
    input_rate: RateMeter
    pairing: ImuPairing
    attitudes: StaticAttitudes
    accepted: int
    last_attempt: CalibrationAttempt | None
    jobs_run: dict[str, int]
    adoptions: dict[str, int]
    tracker: OnlineTracker | None
    tracked_updates: int
    hold_overflows: int
    findings: Findings
    runner: FitRunner

    @property
    def state(self) -> str: ...
    @property
    def held(self) -> int: ...
    @property
    def frame_id(self) -> str: ...
    @property
    def last_residual_pct(self) -> float | None: ...
    def rejects(self) -> dict[str, int]: ...
    def earth_reference(self) -> EarthReference | None: ...


def diagnostic_values(session: ReportedSession, now: float, coverage: Coverage
                      ) -> dict[str, object]:
    """Key/values for /diagnostics, plain numbers and strings; read once per diagnostics
    period (updates the input rates)."""
    calibration = session.calibration
    buffer = session.buffer
    values: dict[str, object] = {
        'state': session.state,
        'coverage_pct': round(100.0 * float(coverage.fraction), 1),
        'coverage_kind': 'heading' if coverage.cells == HEADING_SECTORS else 'direction',
        'coverage_hint': coverage.hint,
        'buffer_fill': int(buffer.fill),
        'buffer_capacity': int(buffer.capacity),
        'relative_knn_distance': round(float(buffer.relative_knn_distance), 5),
        'held_out_readings': len(session.evidence),
        'waiting_readings': session.held,
        'input_rate_hz': round(session.input_rate.read(now), 2),
        'messages_accepted': int(session.accepted),
        'frame_id': session.frame_id,
        'last_residual_pct': ('' if session.last_residual_pct is None
                              else round(session.last_residual_pct, 3)),
        'last_calibrate': '' if session.last_attempt is None else session.last_attempt.message,
        'fits': ', '.join(f'{kind} {count}' for kind, count in sorted(session.jobs_run.items())),
        'adopted': ', '.join(f'{source} {count}'
                             for source, count in sorted(session.adoptions.items())),
    }
    values.update({f'rejected_{k}': int(v) for k, v in session.rejects().items()})
    headroom = could_be_better(session.findings, calibration)
    if headroom is not None:
        values['could_be_better_pct'] = round(headroom[0], 2)
        values['could_be_better'] = headroom[1]
    check = session.misfit.last
    if check is not None and check.judged:
        values['live_median_error_pct'] = round(check.median_error_pct, 2)
    if calibration is not None:
        scale = TESLA_TO_MICROTESLA if session.units == 'T' else 1.0
        unit = display_units(session.units)
        values['model'] = calibration.model
        values[f'offset_{unit}'] = [round(float(v) * scale, 3) for v in calibration.offset]
        values[f'field_strength_{unit}'] = round(float(calibration.field_strength) * scale, 3)
    values.update(session.compensation.diagnostic_values(calibration, session.units,
                                                           session.clock.now))
    if session.tracker is not None:
        values['tracked_updates'] = session.tracked_updates
    if session.hold_overflows:
        values['hold_overflows'] = session.hold_overflows
    if session.runner.restarts:
        values['fit_worker_restarts'] = int(session.runner.restarts)
        values['fit_worker_last_restart'] = session.runner.last_restart
    values.update(_reference_values(session, now))
    return values


def could_be_better(findings: Findings, calibration: Calibration | None
                    ) -> tuple[float, str] | None:
    """How far ``calibration`` (the one in force) is from the latest fit of what the node holds
    that passed its gates, on the same held-out readings: (percent lower residual, what to do);
    None when no such fit was judged against it yet. What the fit of the buffer gives is what
    ``~/calibrate`` puts in force, so a user can act on it; refinement adopts it by itself once
    the gain is beyond noise."""
    headroom = findings.headroom
    if headroom is None or calibration is None or headroom[0] is not calibration:
        return None
    comparison = headroom[1]
    gain = comparison.gain_pct
    if gain is None:
        return None
    gain = max(gain, 0.0)
    if gain < 100.0 * MIN_GAIN:
        return gain, (f'the calibration in force is as good as a fit of the buffer now '
                      f'({comparison.current_pct:.2f} % vs {comparison.candidate_pct:.2f} % on '
                      f'{comparison.readings} held-out readings)')
    why = ('it covers fewer directions than the calibration in force' if comparison.better
           else 'not yet beyond noise')
    return gain, (f'could be better by {gain:.1f} %: a fit of the buffer now has residual '
                  f'{comparison.candidate_pct:.2f} % against {comparison.current_pct:.2f} % on '
                  f'{comparison.readings} held-out readings ({why}); call ~/calibrate to put '
                  'it in force now, or keep turning the sensor for refinement to prove it')


def _reference_values(session: ReportedSession, now: float) -> dict[str, object]:
    """The IMU alignment and the model's field, for /diagnostics."""
    values: dict[str, object] = {}
    pairing = session.pairing
    if pairing.rate.count or pairing.accepted:
        values['imu_rate_hz'] = round(pairing.rate.read(now), 2)
        values['imu_messages_accepted'] = int(pairing.accepted)
        values['imu_messages_refused'] = int(pairing.refused)
        values.update({f'imu_rejected_{k}': int(v) for k, v in pairing.refusals.items()})
        values['readings_paired'] = int(pairing.paired)
        values['imu_samples_accelerating'] = int(pairing.gravity.rejected)
        if pairing.gravity.rates.scale is not None:
            values['imu_turning_share'] = round(pairing.gravity.rates.scale, 3)
        values['imu_warning'] = pairing.warning()
        values['static_attitudes'] = int(session.attitudes.fill)
    calibration = session.calibration
    if calibration is not None and calibration.aligned:
        for key in ('alignment_angle_deg', 'dip_deg', 'dip_std_deg', 'static_samples'):
            number = calibration.metadata_number(key)
            if number is not None:
                values[key] = round(number, 3)
    alignment = session.findings.alignment
    if alignment is not None:
        model = '' if calibration is None else calibration.model
        values['last_alignment'] = ('applied' if alignment.success
                                    else alignment_reason(alignment, model))
    earth = session.findings.earth
    if earth is not None:
        values['earth_model'] = earth.model
        values['model_intensity_uT'] = round(earth.intensity_nt / 1000.0, 3)
        values['model_inclination_deg'] = round(earth.inclination_deg, 3)
        values['declination_deg'] = round(earth.declination_deg, 3)
        reference = session.earth_reference()
        if calibration is not None and reference is not None:
            check = reference.check(calibration.field_radius(),
                                    calibration.metadata_number('dip_deg'))
            if check.radius_ratio is not None:
                values['field_ratio_to_model'] = round(check.radius_ratio, 4)
            if check.dip_error_deg is not None:
                values['dip_error_deg'] = round(check.dip_error_deg, 3)
    return values


__all__ = [
    'NEEDS_TILTS',
    'TESLA_TO_MICROTESLA',
    'UNOBSERVED_WORDS',
    'CalibrationAttempt',
    'NO_INPUT_GRACE_S',
    'Level',
    'ReportedSession',
    'alignment_reason',
    'alignment_text',
    'calibration_summary',
    'could_be_better',
    'coverage_pct',
    'diagnostic_values',
    'diagnostics_level',
    'display_units',
    'format_field',
    'misfit_text',
    'no_input_text',
    'no_message_text',
    'progress_text',
    'reference_text',
    'unobserved_text',
]
