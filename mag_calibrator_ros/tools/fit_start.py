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

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.earth_field import TESLA_PER_UNIT
from mag_calibrator_ros.calibration.fit.fitting import FitResult
from mag_calibrator_ros.calibration.live.evidence import MISFIT_MIN_SPAN, check_fit
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.store.calibration_file import (
    TESLA,
    UNITS_KEY,
    LoadedCalibration,
    read_calibration_file,
)
from mag_calibrator_ros.tools import fit_compensation as own_field
from mag_calibrator_ros.tools.recordings import Recording

HELP = ("start from a saved calibration (a node's calibration_file, or an earlier --output), "
        "as the node does: the answer is the buffer's fit when it passes its gates, else the "
        'calibration in force at the end (this one, as refined and compensated on the way). '
        'Learns the own field from recordings that never turn; checks a saved calibration '
        'against a new recording (exit 1 when it does not fit it)')


CHANGES = {'compensation': 'own field learned', 'refine': 'refined', 'auto': 'recalibrated',
           'realign': 'realigned to the IMU', 'tracking': 'tracked', 'parameters': 'parameters'}
"""What each ``CalibrationSession.adoptions`` source did to the calibration in force."""


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
    """``calibration`` (static part) on ``readings`` without the robot's own field."""
    readings = readings[np.all(np.isfinite(readings), axis=1)]
    verdict = check_fit(calibration, readings, gate_pct)
    strength = calibration.field_strength
    magnitudes = strength * np.linalg.norm(calibration.apply(readings) / strength, axis=1)
    median = (float(np.median(np.abs(magnitudes / strength - 1.0))) * 100.0
              if len(readings) else math.nan)
    off = verdict.off if verdict.judged else not median <= gate_pct
    return RecordingCheck(len(readings), median, verdict.judged, off)


def judged(loaded: LoadedCalibration, answer: Calibration, recording: Recording,
           fit: FitResult, sessions: list[CalibrationSession], gate_pct: float
           ) -> dict[str, Any]:
    """The --json 'start' object: where the ``answer`` came from (the buffer's ``fit``, or
    the calibration in force after what ``sessions`` changed), and it judged on every reading
    of the ``recording`` without its own field."""
    readings = recording.samples
    if answer.compensation is not None:
        readings = own_field.without_own_field(recording, answer.compensation)
    changes: dict[str, int] = {}
    for session in sessions:
        for source, count in session.adoptions.items():
            if source not in ('file', 'request'):
                changes[source] = changes.get(source, 0) + count
    return {'file': str(loaded.path), 'notes': list(loaded.notes),
            'answer': 'buffer fit' if fit.success else 'in force', 'changes_in_force': changes,
            'buffer_fit': fit.reason, 'check': check(answer, readings, gate_pct).as_dict()}


def reason(found: dict[str, Any], gate_pct: float) -> str:
    """Why the answer does not fit the recording (the report's FAILED line)."""
    judged = found['check']
    if judged['judged_by_misfit_rule']:
        return (f"the calibration does not fit this recording: median |B| error "
                f"{judged['median_error_pct']:.2f} % of F, beyond what its own residual "
                'predicts and explained by a new offset (another board, or the iron moved)')
    return (f"the calibration does not fit this recording: median |B| error "
            f"{judged['median_error_pct']:.2f} % of F, over the {gate_pct:g} % gate")


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
                   "residual and coverage below are that fit's)")
    judged = found['check']
    how = ('' if judged['judged_by_misfit_rule'] else
           f' (by magnitude only: a misfit check needs readings over '
           f'{100.0 * MISFIT_MIN_SPAN:.0f} % of directions)')
    out.append(f"check     on all {judged['readings']} readings: median |B| error "
               f"{judged['median_error_pct']:.2f} % of F, "
               f"{'fits' if judged['fits'] else 'does NOT fit'}{how}")
    return out


__all__ = ['RecordingCheck', 'StartError', 'add_argument', 'check', 'in_units', 'judged',
           'lines', 'read', 'reason', 'second_start']
