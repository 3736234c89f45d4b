# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""``mag_calibrator_fit --calibration FILE``: replay a recording on a saved calibration.

The session starts with FILE's calibration in force, as the node does with
``calibration_file``, so the answer is what that robot would hold after the recording and a
``~/calibrate`` at its end: the buffer's own fit when it passes its gates (a request replaces
whatever is in force), else the calibration in force then, FILE's as the session refined,
realigned or compensated it on the way. Two things need this: a recording that never turns (a
hover, a drive straight ahead and back) calibrates nothing by itself, yet can teach the robot's
own field, which is learned only once a calibration is in force (``live/compensation.py``); and
a saved calibration checked against a new recording.

The answer is judged on every reading of the recording, its own field removed, by the live
misfit rule (``evidence.check_fit``: the median |B| error against what the calibration's own
residual predicts, and whether a new offset would explain it). Readings that span too few
directions for that rule are judged by magnitude alone: a median |B| error past the residual
gate does not fit them, whatever their span. A calibration that does not fit is exit 1 and is
never written, as a fit that failed its gates.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import math
from typing import Any

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import Alignment
from mag_calibrator_ros.calibration.fit.calibration import Calibration, Compensation
from mag_calibrator_ros.calibration.fit.earth_field import (
    TESLA_PER_UNIT,
    EarthCheck,
    EarthReference,
)
from mag_calibrator_ros.calibration.fit.fitting import FitResult
from mag_calibrator_ros.calibration.live.compensation import input_columns
from mag_calibrator_ros.calibration.live.evidence import (
    MISFIT_MIN_SPAN,
    check_fit,
    relative_errors,
)
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.store.calibration_file import (
    TESLA,
    UNITS_KEY,
    LoadedCalibration,
    read_calibration_file,
)
from mag_calibrator_ros.tools import fit_compensation as own_field
from mag_calibrator_ros.tools.recording_value import Recording

HELP = ("start from a saved calibration (a node's calibration_file, or an earlier --output), "
        "as the node does: the answer is the buffer's fit when it passes its gates, else the "
        'calibration in force at the end (this one, as refined and compensated on the way). '
        'Learns the own field from recordings that never turn (with their gyroscope); checks a '
        'saved calibration against a new recording (exit 1 when it does not fit it)')


CHANGES = {'compensation': 'own field learned', 'refine': 'refined', 'auto': 'recalibrated',
           'realign': 'realigned to the IMU', 'tracking': 'tracked'}
"""What each source of ``SessionCounts.adoptions`` did to the calibration in force."""


class StartError(ValueError):
    """--calibration cannot be used with this run; the message says why and what to do."""


def add_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--calibration', metavar='FILE', default=None, help=HELP)


def read(args: argparse.Namespace) -> LoadedCalibration | None:
    """FILE's calibration (in tesla, as saved), before any recording is read; None without
    --calibration. A missing or invalid file raises ``CalibrationFileError`` (exit 2)."""
    if args.calibration is None:
        return None
    if args.all:
        raise StartError('--calibration starts the live session; it has no effect with --all')
    return read_calibration_file(args.calibration)


def in_units(loaded: LoadedCalibration, units: str, source: str) -> Calibration:
    """The saved calibration (tesla) for readings in the recording's ``units``."""
    if units == TESLA:
        return loaded.calibration
    if units not in TESLA_PER_UNIT:
        raise StartError(
            f'--calibration is in tesla, but {source} does not say its unit: give it with '
            '--units uT|nT|G|mG|T, or the tesla per count of raw counts with --scale')
    return loaded.calibration.scaled(1.0 / TESLA_PER_UNIT[units]).with_metadata(
        **{UNITS_KEY: units})


def second_start(first: CalibrationSession) -> Calibration | None:
    """Where the second pass (readings without the own field learned) starts: the static part
    of what the first pass held in force, whose offset belongs with the compensation learned."""
    return None if first.calibration is None else first.calibration.with_compensation(None)


@dataclass(frozen=True)
class RecordingCheck:
    """A calibration judged on a whole recording (see the module's docstring)."""

    readings: int
    median_error_pct: float
    judged: bool
    """By the live misfit rule (the readings span enough directions); else by magnitude."""
    off: bool

    def as_dict(self) -> dict[str, Any]:
        return {'readings': self.readings, 'median_error_pct': self.median_error_pct,
                'judged_by_misfit_rule': self.judged, 'fits': not self.off}


def check(calibration: Calibration, readings: np.ndarray, gate_pct: float) -> RecordingCheck:
    """``calibration`` (static part) on ``readings`` without the robot's own field: off when
    the live misfit rule says so, or when the median |B| error is past the residual gate."""
    readings = readings[np.all(np.isfinite(readings), axis=1)]
    verdict = check_fit(calibration, readings, gate_pct)
    errors = relative_errors(calibration, readings)
    median = float(np.median(np.abs(errors))) * 100.0 if len(readings) else math.nan
    off = (verdict.judged and verdict.off) or not median <= gate_pct
    return RecordingCheck(len(readings), median, verdict.judged, off)


def unfed(compensation: Compensation, recording: Recording) -> list[str]:
    """What ``compensation`` needs that the recording does not log: its inputs (matched as the
    node matches them), the temperature for its temperature term."""
    missing = []
    if np.any(compensation.interference) and (
            recording.inputs is None
            or input_columns(compensation.inputs, recording.input_names) is None):
        missing.append(', '.join(compensation.inputs))
    if (compensation.reference_temperature is not None
            and np.any(compensation.temperature_coefficient) and recording.temperature is None):
        missing.append('the temperature')
    return missing


def _without(compensation: Compensation, missing: list[str]) -> Compensation | None:
    """``compensation`` without the terms of what the recording does not log."""
    gains, drift = compensation.interference, compensation.temperature_coefficient
    if 'the temperature' in missing:
        drift = np.zeros(3)
    if any(item != 'the temperature' for item in missing):
        gains = np.zeros_like(gains)
    if not (np.any(gains) or np.any(drift)):
        return None
    return Compensation(compensation.inputs, gains, drift,
                        compensation.reference_temperature if np.any(drift) else None)


def answer(loaded: LoadedCalibration, sessions: tuple[CalibrationSession, CalibrationSession],
           recording: Recording, fit: FitResult, gate_pct: float
           ) -> tuple[Calibration, dict[str, Any]]:
    """The calibration the node would hold at the recording's end (the second of ``sessions``,
    with the compensation the first learned), and the --json 'start' object: where it came
    from, and it judged on every reading without its own field.

    A term of the file's compensation the recording cannot feed (it does not log its input, or
    the temperature) goes with the file's static part, but not with a fit of this recording:
    that fit holds the term's field in its offset, and the term would take it off twice."""
    learner, session = sessions
    calibration = own_field.with_learned(session.calibration, learner)
    compensation = calibration.compensation
    own = 'learned' if own_field.learned(learner) is not None else None
    if own is None and compensation is not None:
        missing = unfed(compensation, recording)
        names = ' and '.join(missing)
        if not missing:
            own = "the file's, applied to the recording's inputs"
        elif fit.success:
            calibration = calibration.with_compensation(_without(compensation, missing))
            own = (f"the file's, without the terms of {names}: the recording does not log "
                   'them, so the fit of it holds their field in its offset')
        else:
            own = f"the file's, kept (the recording does not log {names})"
    readings = (recording.samples if calibration.compensation is None
                else own_field.without_own_field(recording, calibration.compensation))
    changes: dict[str, int] = {}
    for each in {id(each): each for each in sessions}.values():  # one, or two passes
        for source, count in each.report().counts.adoptions.items():
            if source not in ('file', 'request'):
                changes[source] = changes.get(source, 0) + count
    found = {'file': str(loaded.path), 'notes': list(loaded.notes),
             'answer': 'buffer fit' if fit.success else 'in force', 'changes_in_force': changes,
             'buffer_fit': fit.reason, 'compensation': own,
             'check': check(calibration, readings, gate_pct).as_dict()}
    return calibration, found


def in_force_reference(session: CalibrationSession, calibration: Calibration,
                       reference: EarthReference | None
                       ) -> tuple[Alignment | None, EarthCheck | None]:
    """The alignment and model check of an answer that is the calibration in force (the
    buffer's fit failed, so its own say nothing about the answer), as the node's diagnostics
    show them: the alignment of the latest fit that passed its own gates on the way, adopted
    or not (None when none did: the file's mounting stands), and the calibration against the
    model."""
    earth_check = None if reference is None else reference.check(
        calibration.field_radius(), calibration.metadata_number('dip_deg'))
    return session.report().alignment, earth_check


def reason(found: dict[str, Any], gate_pct: float) -> str:
    """Why the answer does not fit the recording (the report's FAILED line)."""
    error = found['check']['median_error_pct']
    if error <= gate_pct:
        return (f'the calibration does not fit this recording: median |B| error {error:.2f} % '
                'of F, beyond what its own residual predicts and explained by a new offset '
                '(another board, or the iron moved)')
    return (f'the calibration does not fit this recording: median |B| error {error:.2f} % of '
            f'F, over the {gate_pct:g} % gate')


def lines(found: dict[str, Any] | None) -> list[str]:
    """The readable report's lines of the starting calibration."""
    if found is None:
        return []
    out = [f"start     {found['file']}: in force from the first reading (as the node's "
           'calibration_file)']
    out += [f'          note: {note}' for note in found['notes']]
    if found['answer'] == 'buffer fit':
        out.append("answer    the buffer's own fit (it passed its gates and replaces the file's)")
    else:
        changed = ', '.join(f'{CHANGES.get(source, source)} {count}x' for source, count in
                            found['changes_in_force'].items())
        out.append("answer    the calibration in force at the end: the file's"
                   + (f', changed by: {changed}' if changed else ', unchanged'))
        out.append(f"          (the buffer's own fit did not pass: {found['buffer_fit']}; the "
                   "residual and coverage below are that fit's, the alignment and earth lines "
                   "the calibration in force's)")
    if found['compensation'] is not None:
        out.append(f"          own field: {found['compensation']}")
    verdict = found['check']
    how = ('' if verdict['judged_by_misfit_rule'] else
           f' (by magnitude only: a misfit check needs readings over '
           f'{100.0 * MISFIT_MIN_SPAN:.0f} % of directions)')
    out.append(f"check     on all {verdict['readings']} readings: median |B| error "
               f"{verdict['median_error_pct']:.2f} % of F, "
               f"{'fits' if verdict['fits'] else 'does NOT fit'}{how}")
    return out


__all__ = ['RecordingCheck', 'StartError', 'add_argument', 'answer', 'check', 'in_force_reference',
           'in_units', 'lines', 'read', 'reason', 'second_start', 'unfed']
