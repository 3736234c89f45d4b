# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The session's state in words and numbers for people: log lines, service answers, /diagnostics.

Nothing here decides anything; every text a user reads about a calibration is built here, so a
wording is changed in one place (tests and users match on these texts: change them with care).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

from mag_calibrator_ros.calibration.fit.alignment import (
    Alignment,
    StaticAttitudes,
    rotation_angle_deg,
)
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.compensation import interference_grade
from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS, Coverage
from mag_calibrator_ros.calibration.fit.earth_field import EarthCheck, EarthField, EarthReference
from mag_calibrator_ros.calibration.fit.heading import COMPLETE_HEADING_COVERAGE
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.error_model import (
    Accuracy,
    ErrorModel,
    calibration_accuracy,
)
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


def calibration_summary(calibration: Calibration, units: str = 'T',
                        earth: EarthField | None = None) -> str:
    """One line: model, offset, residual % and coverage % (when the fit recorded them), and
    what it is worth for a heading by its own numbers (at the model's dip when none was
    measured)."""
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
    inclination = None if earth is None else earth.inclination_deg
    text += ', ' + calibration_accuracy(calibration, inclination).text()
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
    text += interference_text(calibration.metadata_number('compensation_interference_pct'))
    learned = calibration.metadata.get('compensation_time')
    return text + (f' (learned {learned})' if learned else '')


def interference_text(pct: float | None) -> str:
    """'; the inputs' field over their ranges is x % of F (ArduPilot's compassmot scale:
    <grade>)' ('' without one): the size of the robot's own field on a scale users know."""
    if pct is None:
        return ''
    return (f"; the inputs' field over their ranges is {pct:.1f} % of F (ArduPilot's "
            f'compassmot scale: {interference_grade(pct)})')


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


def world_text(check: FitCheck | None, units: str) -> str:
    """A misfit that is the world's (``MisfitMonitor.world``): what is seen and what is kept."""
    measured = '?' if check is None or not check.judged else format_field(
        check.measured_field, units)
    expected = '?' if check is None else format_field(check.expected_field, units)
    return (f'the field around the sensor is disturbed: |B| {measured} vs {expected} expected, '
            "while the gyroscope's turning says the sensor's offset has not changed - a magnet, "
            'steel or a vehicle nearby? The calibration stays in force (its output marked '
            'uncertain) and nothing is learned until the field fits it again')


LEFT_PLANE_TEXT = ('the sensor moved out of the plane it was calibrated turning in: collecting '
                   'in 3-D for a full calibration (keep turning it through every orientation); '
                   'the planar calibration stays in force until a better one is found')


def set_aside_text(source: str, refused: int, window: int) -> str:
    """Why the buffer stopped screening by its reference (``BufferReference.stale``)."""
    what = 'its own fit' if source == 'fit' else 'the calibration in force'
    return (f'the buffer stopped screening by {what}: it refused {refused} of the last {window} '
            'readings, so it no longer describes the sensor; collecting without it')


NO_INPUT_GRACE_S = 3.0
"""No 'no input' line before this long (nor a progress period) without message or publisher:
discovering a driver that is already running takes a moment."""


def no_input_text(topic: str, elsewhere: Sequence[str] = ()) -> str:
    """'no input on ...', naming the MagneticField topics published ``elsewhere`` (a remap or a
    namespace away) when there are any."""
    if elsewhere:
        names = ', '.join(elsewhere[:3])
        return (f'no input on {topic}; sensor_msgs/MagneticField is published on {names}: remap '
                f'to it (-r imu/mag:={elsewhere[0]}) or start the node in its namespace')
    return (f'no input on {topic}: is the driver running, in this namespace? '
            f'(ros2 topic info {topic})')


def no_message_text(topic: str, publishers: int, first: bool, waited_s: float,
                    period_s: float, elsewhere: Sequence[str] = ()) -> str | None:
    """The progress line when no message came since the previous one (``first``: none ever):
    waiting while ``topic`` has publishers; 'no input' once ``waited_s`` since start-up reached
    a progress period and NO_INPUT_GRACE_S without either; None (nothing to say) before."""
    if publishers:
        return (f'waiting for {"the first" if first else "a"} message on {topic} '
                f'({publishers} publisher(s) found)')
    if waited_s < max(period_s, NO_INPUT_GRACE_S):
        return None
    return no_input_text(topic, elsewhere)


def progress_text(state: str, calibration: Calibration | None, coverage: Coverage,
                  buffer: SampleBuffer, settings: SessionSettings, held_back: str = '') -> str:
    """What to do next, e.g. 'coverage 63 % - keep rotating about the pitch axis (y)';
    ``held_back``, said instead while uncalibrated: why nothing can go in force yet (input no
    fit can fix, or the first calibration waiting to be aligned to the IMU)."""
    if calibration is None and held_back:
        return held_back
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
                      imu_warning: str = '', input_problem: str = '', node_warning: str = ''
                      ) -> tuple[Level, str]:
    """The level and message of the calibrator's /diagnostics status: the first that applies of
    a problem of the node or its fit worker (ERROR), a warning of the node (another publisher
    on its output: ``nodes/graph_watch.py``), input no calibration can fix (wrong unit,
    normalised: ``sanity.py``), messages refused since the last report, a misfit, a disturbed
    field, a mounting error, an IMU that cannot be paired (WARN), calibrated (OK), no input,
    still calibrating (WARN)."""
    if problem is not None:
        return 'ERROR', problem
    if node_warning:
        return 'WARN', f'{state}: {node_warning}'
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


@dataclass(frozen=True)
class NodeStatus:
    """What the node adds to a report: its own problem (a file or parameter error, shown as
    ERROR), its warning (WARN: another node doubles its output), the 'no input' text in its
    topic's words, and its /diagnostics values (the file, the turn, the location), after the
    session's."""

    problem: str | None = None
    no_input: str = ''
    values: Mapping[str, object] = field(default_factory=dict)
    warning: str = ''


@dataclass(frozen=True)
class BufferReport:
    """The uniqueness buffer: how full, what it has seen and merged, what it screens by."""

    fill: int
    capacity: int
    k: int
    seen: int
    """Readings offered to the buffer (the rest of those accepted were held out)."""
    merged: int
    evicted: int
    readings_held: float
    """Readings the samples stand for (the sum of their merge counts)."""
    merging: bool
    screened_by: str | None
    """What the buffer screens readings by: 'fit' (its own), 'calibration' (the one in force)
    or None."""


@dataclass(frozen=True)
class ImuReport:
    """The accelerometer and gyroscope stream the readings are paired with."""

    received: int
    """Samples given to ``process_imu``, refused ones included."""
    accepted: int
    refusals: Mapping[str, int]
    """Samples refused, by reason (``pairing.IMU_REASONS``)."""
    paired: int
    """Magnetometer readings paired with an accelerometer sample."""
    waiting: int
    """Readings waiting for a later sample to pair with."""
    accelerating: int
    """Samples that measured no gravity (the robot accelerating)."""
    static_attitudes: int
    warning: str
    gyro_problem: str
    """Why the gyroscope does not turn with the accelerometer ('' when it does)."""
    gyro_in_degrees: bool

    @property
    def refused(self) -> int:
        return sum(self.refusals.values())


@dataclass(frozen=True)
class SessionCounts:
    """Messages and decisions counted since the session began."""

    received: int
    """Messages given to ``process``, refused ones included."""
    accepted: int
    rejects: Mapping[str, int]
    """Every refusal by reason: screening, then duplicates and magnitude outliers."""
    adoptions: Mapping[str, int]
    """How often a calibration went in force, by source (auto, refine, request, file ...)."""
    fits: Mapping[str, int]
    """Fits run, by kind (calibrate, refine, check, reference, compensate, request)."""
    held: int
    """Readings received while a fit ran, not yet learnt from (fed in order, later)."""
    hold_overflows: int
    held_out: int
    """Held-out readings kept to judge calibrations on."""
    stale_dropped: int
    """Readings dropped unlearnt: compensated by a compensation no longer in force."""
    tracked_updates: int


@dataclass(frozen=True)
class SessionReport:
    """The session for people and tools at one moment: a frozen value, built here from the
    session's parts (``CalibrationSession.report``), read once per diagnostics period by the
    node and whenever a tool or test asks."""

    state: str
    calibration: Calibration | None
    progress: str
    """What to do next, e.g. 'coverage 63 % - keep rotating about the pitch axis (y)'."""
    level: Level
    message: str
    """/diagnostics' level and message: the first problem that applies, else the progress."""
    values: Mapping[str, object]
    """/diagnostics' key/values (the node's after the session's)."""
    coverage: Coverage
    frame_id: str
    """The stream's frame, '' while unknown."""
    input_rate_hz: float
    counts: SessionCounts
    buffer: BufferReport
    imu: ImuReport
    misfit: str
    """Why the calibration in force does not fit ('' unless judged so)."""
    earth_warning: str
    alignment_warning: str
    input_problem: str
    """Input no calibration can fix (a wrong unit, a normalised stream: ``sanity.py``)."""
    earth: EarthField | None
    """The World Magnetic Model's field here (``set_earth_field``), None while unknown."""
    alignment: Alignment | None
    """The latest alignment to the IMU a fit that passed its gates found."""
    earth_check: EarthCheck | None
    """The latest such fit against the World Magnetic Model."""
    last_attempt: CalibrationAttempt | None
    compensation_needs: str
    """What motion or wait the latest own-field fit needed ('' if none)."""
    tracking: bool
    """Whether online tracking follows the calibration in force."""
    waiting_for_alignment: bool
    accuracy: Accuracy
    """What the calibration in force is worth for a heading now (``error_model.py``)."""


class ReportInputs(NamedTuple):
    """The session's parts a report reads, handed over by ``CalibrationSession.report`` (the
    session imports this module; its parts stay its own)."""

    settings: SessionSettings
    units: str
    state: str
    calibration: Calibration | None
    buffer: SampleBuffer
    screened_by: str | None
    evidence: HeldOutEvidence
    misfit: MisfitMonitor
    errors: ErrorModel
    input_rate: RateMeter
    pairing: ImuPairing
    attitudes: StaticAttitudes
    counts: SessionCounts
    last_attempt: CalibrationAttempt | None
    tracker: OnlineTracker | None
    findings: Findings
    earth_reference: EarthReference | None
    compensation_values: Mapping[str, object]
    compensation_needs: str
    runner: FitRunner
    input_values: Mapping[str, object]
    """The input checks' and the alignment wait's /diagnostics values."""
    input_problem: str
    waiting_for_alignment: bool
    frame_id: str
    progress: str
    earth_warning: str


def session_report(parts: ReportInputs, now: float | None, coverage: Coverage,
                   node: NodeStatus | None, refused: Mapping[str, int] | None
                   ) -> SessionReport:
    """The report of ``parts``; ``now`` (the node's clock, seconds) measures the input rates
    since the previous report that had one, None keeps the latest measured. ``refused``:
    messages refused by screening since the previous such report."""
    node = node or NodeStatus()
    misfit = (world_text(parts.misfit.last, parts.units) if parts.misfit.world else
              misfit_text(parts.misfit.last, parts.units, parts.settings.auto_calibrate))
    earth = parts.findings.earth
    accuracy = parts.errors.accuracy(
        parts.calibration, None if earth is None else earth.inclination_deg,
        parts.misfit.uncertainty, misfit if parts.misfit.misfit else '')
    values = {**diagnostic_values(parts, now, coverage), **accuracy.values(),
              **parts.input_values, **node.values}
    input_rate_hz = float(values['input_rate_hz'])
    pairing, input_problem = parts.pairing, parts.input_problem
    problem = '; '.join(text for text in (node.problem, parts.runner.problem) if text) or None
    level, message = diagnostics_level(
        parts.state, parts.progress, input_rate_hz, node.no_input, problem=problem,
        refused=refused if problem is None else None, misfit=misfit,
        earth_warning=parts.earth_warning,
        alignment_warning=parts.findings.alignment_warning, imu_warning=pairing.warning(),
        input_problem=input_problem, node_warning=node.warning)
    buffer = parts.buffer
    rates = pairing.gravity.rates
    return SessionReport(
        state=parts.state, calibration=parts.calibration, progress=parts.progress,
        level=level, message=message, values=values, coverage=coverage,
        frame_id=parts.frame_id, input_rate_hz=input_rate_hz, counts=parts.counts,
        buffer=BufferReport(
            fill=int(buffer.fill), capacity=int(buffer.capacity), k=int(buffer.k),
            seen=int(buffer.seen), merged=int(buffer.merged), evicted=int(buffer.evicted),
            readings_held=float(buffer.counts.sum()), merging=bool(buffer.merging),
            screened_by=parts.screened_by),
        imu=ImuReport(
            received=int(pairing.rate.count), accepted=int(pairing.accepted),
            refusals=dict(pairing.refusals),
            paired=int(pairing.paired), waiting=int(pairing.waiting),
            accelerating=int(pairing.gravity.rejected),
            static_attitudes=int(parts.attitudes.fill), warning=pairing.warning(),
            gyro_problem=rates.problem(), gyro_in_degrees=bool(rates.looks_like_degrees)),
        misfit=misfit, earth_warning=parts.earth_warning,
        alignment_warning=parts.findings.alignment_warning, input_problem=input_problem,
        earth=parts.findings.earth, alignment=parts.findings.alignment,
        earth_check=parts.findings.earth_check,
        last_attempt=parts.last_attempt, compensation_needs=parts.compensation_needs,
        tracking=parts.tracker is not None, waiting_for_alignment=parts.waiting_for_alignment,
        accuracy=accuracy)


def diagnostic_values(parts: ReportInputs, now: float | None, coverage: Coverage
                      ) -> dict[str, object]:
    """Key/values for /diagnostics, plain numbers and strings (``session_report``'s ``now``)."""
    calibration = parts.calibration
    buffer = parts.buffer
    counts = parts.counts
    residual = None if calibration is None else calibration.metadata_number('residual_rms_pct')
    values: dict[str, object] = {
        'state': parts.state,
        'coverage_pct': round(100.0 * float(coverage.fraction), 1),
        'coverage_kind': 'heading' if coverage.cells == HEADING_SECTORS else 'direction',
        'coverage_hint': coverage.hint,
        'buffer_fill': int(buffer.fill),
        'buffer_capacity': int(buffer.capacity),
        'relative_knn_distance': round(float(buffer.relative_knn_distance), 5),
        'held_out_readings': counts.held_out,
        'waiting_readings': counts.held,
        'input_rate_hz': round(_rate(parts.input_rate, now), 2),
        'messages_accepted': int(counts.accepted),
        'frame_id': parts.frame_id,
        'last_residual_pct': '' if residual is None else round(residual, 3),
        'last_calibrate': '' if parts.last_attempt is None else parts.last_attempt.message,
        'fits': ', '.join(f'{kind} {count}' for kind, count in sorted(counts.fits.items())),
        'adopted': ', '.join(f'{source} {count}'
                             for source, count in sorted(counts.adoptions.items())),
    }
    values.update({f'rejected_{k}': int(v) for k, v in counts.rejects.items()})
    headroom = could_be_better(parts.findings, calibration)
    if headroom is not None:
        values['could_be_better_pct'] = round(headroom[0], 2)
        values['could_be_better'] = headroom[1]
    check = parts.misfit.last
    if check is not None and check.judged:
        values['live_median_error_pct'] = round(check.median_error_pct, 2)
    if calibration is not None:
        scale = TESLA_TO_MICROTESLA if parts.units == 'T' else 1.0
        unit = display_units(parts.units)
        values['model'] = calibration.model
        values[f'offset_{unit}'] = [round(float(v) * scale, 3) for v in calibration.offset]
        values[f'field_strength_{unit}'] = round(float(calibration.field_strength) * scale, 3)
    values.update(parts.compensation_values)
    if parts.tracker is not None:
        values['tracked_updates'] = counts.tracked_updates
    if counts.hold_overflows:
        values['hold_overflows'] = counts.hold_overflows
    if parts.runner.restarts:
        values['fit_worker_restarts'] = int(parts.runner.restarts)
        values['fit_worker_last_restart'] = parts.runner.last_restart
    values.update(_reference_values(parts, now))
    return values


def _rate(meter: RateMeter, now: float | None) -> float:
    """Messages per second since the previous reading of ``meter`` (``now``), or the latest."""
    return meter.rate if now is None else meter.read(now)


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


def _reference_values(parts: ReportInputs, now: float | None) -> dict[str, object]:
    """The IMU alignment and the model's field, for /diagnostics."""
    values: dict[str, object] = {}
    pairing = parts.pairing
    if pairing.rate.count or pairing.accepted:
        values['imu_rate_hz'] = round(_rate(pairing.rate, now), 2)
        values['imu_messages_accepted'] = int(pairing.accepted)
        values['imu_messages_refused'] = int(pairing.refused)
        values.update({f'imu_rejected_{k}': int(v) for k, v in pairing.refusals.items()})
        values['readings_paired'] = int(pairing.paired)
        values['imu_samples_accelerating'] = int(pairing.gravity.rejected)
        if pairing.gravity.rates.scale is not None:
            values['imu_turning_share'] = round(pairing.gravity.rates.scale, 3)
        values['imu_warning'] = pairing.warning()
        values['static_attitudes'] = int(parts.attitudes.fill)
    for stream, lags in (('imu', pairing.imu_lags), ('mag', pairing.mag_lags)):
        lag = lags.after_sent()  # live only: how late this node handles the stream
        if lag is not None:
            values[f'{stream}_handled_after_s'] = round(lag, 4)
    calibration = parts.calibration
    if calibration is not None and calibration.aligned:
        for key in ('alignment_angle_deg', 'dip_deg', 'dip_std_deg', 'static_samples'):
            number = calibration.metadata_number(key)
            if number is not None:
                values[key] = round(number, 3)
    alignment = parts.findings.alignment
    if alignment is not None:
        model = '' if calibration is None else calibration.model
        values['last_alignment'] = ('applied' if alignment.success
                                    else alignment_reason(alignment, model))
    earth = parts.findings.earth
    if earth is not None:
        values['earth_model'] = earth.model
        values['model_intensity_uT'] = round(earth.intensity_nt / 1000.0, 3)
        values['model_inclination_deg'] = round(earth.inclination_deg, 3)
        values['declination_deg'] = round(earth.declination_deg, 3)
        reference = parts.earth_reference
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
    'LEFT_PLANE_TEXT',
    'NO_INPUT_GRACE_S',
    'Level',
    'BufferReport',
    'ImuReport',
    'NodeStatus',
    'ReportInputs',
    'SessionCounts',
    'SessionReport',
    'alignment_reason',
    'alignment_text',
    'calibration_summary',
    'could_be_better',
    'coverage_pct',
    'diagnostic_values',
    'session_report',
    'set_aside_text',
    'diagnostics_level',
    'display_units',
    'format_field',
    'misfit_text',
    'world_text',
    'no_input_text',
    'no_message_text',
    'progress_text',
    'reference_text',
    'unobserved_text',
]
