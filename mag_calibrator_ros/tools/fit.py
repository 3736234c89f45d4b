# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""``mag_calibrator_fit``: calibrate a magnetometer offline from a recording.

The recording (text or rosbag2, see :mod:`mag_calibrator_ros.tools.recordings`) is streamed through
the calibrator node's own :class:`CalibrationSession` (sample buffer, its reference fits,
automatic calibration and refinement, at the same readings as the node) and the buffer is then
fitted as the node does on ``~/calibrate``, so an offline result predicts what the robot gets;
or, with ``--all``, every reading, one per place (``coverage.places``: pauses weigh as moves).
The calibration is reported in the recording's own units; ``--output`` writes it in tesla, the
node's unit, so it needs the recording's unit (``--units``, a header such as ``Magnetometer X
(uT)``, a bag or ``ros2 topic echo``: tesla) or
the tesla per count of raw counts (``--scale``, which converts the samples to tesla as they are
read).

With ``--accel-columns`` (a text log with the accelerometer on each line, its gyroscope with
``--gyro-columns``) or ``--accel`` (a bag's Imu topic, paired by stamp) the calibration is
aligned to the accelerometer from the readings held still, as the node does with imu/data_raw;
with ``--latitude``/``--longitude`` it is checked against the World Magnetic Model there. A
recording that logs the current or the sensor temperature (columns by header name, or a bag's
BatteryState / Temperature topics) also teaches the robot's own field, K and c, as the node
learns them (``fit_compensation.py``); the buffer fitted is then that of a second pass over the
readings without them.

Time: a bag's header stamps or a log's time column time the live session and tell still
readings; the summary says which. A log without time has no rate anyone knows: its rows are
replayed ``--rate`` apart (default 100 Hz) for the session's timing only, and its still
readings are found without a clock (``StaticAttitudes(clock=False)``), so no ``--rate`` makes or
breaks its alignment.

With ``--calibration FILE`` the session starts from a saved calibration, as the node does with
``calibration_file``, and the answer is what that node would hold at the recording's end
(``fit_start.py``).

Exit codes: 0 calibrated; 1 the fit failed a quality gate (the best-effort numbers are printed,
marked NOT passing, and no calibration file is written: a robot must never load a calibration
that failed its gates), or with ``--calibration`` the answer does not fit the recording; 2 usage
or input errors (one line on stderr, no traceback).
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
import json
import math
import os
from pathlib import Path
import sys
from typing import Any, NoReturn, TextIO

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import Alignment, StaticAttitudes
from mag_calibrator_ros.calibration.fit.calibration import MODELS, Calibration
from mag_calibrator_ros.calibration.fit.coverage import places
from mag_calibrator_ros.calibration.fit.earth_field import (
    MAX_DIP_ERROR_DEG,
    MAX_FIELD_ERROR_PCT,
    TESLA_PER_UNIT,
    EarthCheck,
    EarthField,
    EarthFieldError,
    EarthReference,
    earth_field,
)
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, FitResult
from mag_calibrator_ros.calibration.fit.input_sanity import (
    field_unit_problem,
    normalised_problem,
    stated_unit_note,
)
from mag_calibrator_ros.calibration.live.buffer import DEFAULT_CAPACITY, DEFAULT_K
from mag_calibrator_ros.calibration.live.error_model import Accuracy, calibration_accuracy
from mag_calibrator_ros.calibration.live.gravity import GravityTracker, RateCheck
from mag_calibrator_ros.calibration.live.jobs import FitJob, run_job
from mag_calibrator_ros.calibration.live.offline import calibrate_now
from mag_calibrator_ros.calibration.live.pairing import ImuPairing, force_problem
from mag_calibrator_ros.calibration.live.screening import VALUE_REASONS, reading_problem
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.store.calibration_file import (
    TESLA,
    UNITS_KEY,
    CalibrationFileError,
    save_calibration,
)
from mag_calibrator_ros.tools import fit_compensation as own_field
from mag_calibrator_ros.tools import fit_start
from mag_calibrator_ros.tools.recording_bags import is_rosbag
from mag_calibrator_ros.tools.recording_text import RATE_UNITS, read_paired_recording
from mag_calibrator_ros.tools.recording_time import row_step
from mag_calibrator_ros.tools.recording_value import Recording, RecordingError, describe_skips
from mag_calibrator_ros.tools.recordings import read_recording

PROG = 'mag_calibrator_fit'
EXIT_CALIBRATED = 0
EXIT_FAILED_GATES = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

DEFAULT_OPTIONS = FitOptions()
PROGRESS_MIN_ROWS = 20_000
"""Fewer rows than this stream through the buffer too quickly for a progress bar to help."""
PROGRESS_MIN_BYTES = 1 << 20
PROGRESS_CHUNK = 2048
DEFAULT_RATE_HZ = 100.0
OUTPUT_SECTION = '/**'
"""--output files apply to any node they are given to with --params-file (any name, any
namespace): which robot a recording came from is the user's to say, by the file they pass."""
REJECT_WORDS = {
    'non_finite': 'NaN/Inf',
    'zero': 'all-zero',
    'saturated': 'at or beyond --full-scale',
    'out_of_range': 'beyond any magnetometer (|value| > 1e12) or, in tesla, below any field',
    'duplicate': 'exact duplicates of a buffered sample',
    'magnitude_outlier': 'magnitude outliers',
}

EPILOG = f"""\
examples:
  {PROG} mag.txt                          fit through the node's sample buffer (default)
  {PROG} mag.txt --all --model full        fit every sample with hard + soft iron
  {PROG} log.tsv --columns 3,4,5 --output mag_calibration.yaml --plot mag.png
  {PROG} log.txt --columns 1,3,5           lines such as "Mx 144 My -270 Mz 415"
  {PROG} log.csv --units uT -o cal.yaml  a log in microtesla; the file is written in tesla
  {PROG} counts.csv --scale 0.15e-6 -o cal.yaml    raw counts of 0.15 uT (AK09916)
  {PROG} ~/bags/run1 --topic /imu/mag --output cal.yaml    rosbag2 (sqlite3 or mcap), tesla
  ros2 topic echo /imu/mag | {PROG} - --json    messages on stdin (tesla), JSON summary
  {PROG} drive.csv --units uT -o cal.yaml    with current and temperature columns: K and c too
  {PROG} drive_bag --battery-topic /battery    a bag's BatteryState current (and Temperature)
  {PROG} hover_bag --accel /imu --calibration cal.yaml -o cal_k.yaml
                                           K from a drive that never turns, on a saved
                                           calibration (exit 1 if it does not fit the drive)
  ros2 topic echo --csv /imu/mag | {PROG} -    the same as CSV (the field is found by itself)
  {PROG} cal_output_2.log --accel-columns 0,1,2 --rate 3 --latitude 45.5 --longitude -122.7
                                           align to the accelerometer logged beside the
                                           magnetometer (3 rows/s) and check against the WMM

field strength F (|corrected| = F): by default the fitted mean radius (magnitude kept, in input
units); --normalise makes F = 1; --field-strength F sets it (e.g. the local field from WMM in the
input's units).

units: the summary is in the input's units; --output is in tesla (the node's unit), converted
from the input's unit: --units (uT, nT, G, mG, T), a header naming it ("Magnetometer X (uT)"), or
tesla for a bag and ros2 topic echo. Raw counts need --scale TESLA_PER_COUNT (the samples are
converted to tesla as they are read; --full-scale and --field-strength are given in counts).
--output with the unit unknown is refused: the node would read the numbers as tesla.

exit status:
  0  calibrated (passed every quality gate; --output written)
  1  the fit failed a quality gate: the best-effort result is printed, marked NOT passing, with
     the reason (e.g. which rotation is missing); --output is NOT written (an existing file is
     left untouched) because a robot must never load a failed calibration; --plot is written.
     With --calibration: the answer (the buffer's fit, else the calibration in force at the
     end) does not fit the recording's readings
  2  usage or input error (missing/unreadable file, too few rows, bad --columns, --output
     without the input's unit, an unwritable --output or --plot ...), or input no
     calibration can fix: readings that cannot be in their unit (0.5 "T" is gauss), or a field
     already normalised or calibrated upstream (|B| constant over every direction)
"""


class _OneLineParser(argparse.ArgumentParser):
    """Usage errors as one line on stderr, exit status 2, as every other input error."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


class UsageError(ValueError):
    """Options that do not fit together or the input; reported as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog=PROG,
        description=(
            'Calibrate a magnetometer offline from a recording: hard iron (offset b) and soft '
            'iron (matrix M), so that corrected = M (raw - b) has magnitude F. Reads CSV/TSV/'
            'whitespace text (header or not, CRLF, labelled lines), "-" for stdin, or a rosbag2 '
            'bag (directory, .db3 or .mcap) with a sensor_msgs/MagneticField topic. By default '
            'the samples stream through the same sample buffer as the calibrator node and the '
            'buffer is fitted as the node does on ~/calibrate.'
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument('input', help='recording: text file, rosbag2 bag directory/.db3/.mcap, '
                        'or - for text on stdin')
    parser.add_argument('--model', choices=MODELS, default=DEFAULT_OPTIONS.model,
                        help='calibration model: full (hard + symmetric soft iron), axis (the '
                        'axis-aligned least squares of mag-calibrator-rs), sphere (hard iron '
                        'only), planar '
                        '(motion in one plane, e.g. a ground robot turning in place), auto '
                        '(chosen by an information criterion; default)')
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument('--buffer', type=int, metavar='N', default=None,
                      help='stream every sample through the live session with a buffer of N '
                      'points and fit the buffer, exactly as the node does (the default mode; '
                      f'N={DEFAULT_CAPACITY})')
    mode.add_argument('--all', action='store_true',
                      help='fit every reading (one per place: pauses weigh as moves) instead '
                           'of the buffer')
    parser.add_argument('--k', type=int, default=None,
                        help=f"neighbours in the buffer's uniqueness score (default {DEFAULT_K})")
    strength = parser.add_mutually_exclusive_group()
    strength.add_argument('--field-strength', type=float, metavar='F', default=None,
                          help='|corrected| = F in input units (default: the fitted mean radius)')
    strength.add_argument('--normalise', '--normalize', action='store_true',
                          help='F = 1 (unit-length corrected field, as mag-calibrator-rs)')
    parser.add_argument('--rate', type=float, metavar='HZ', default=None,
                        help='a text log without a time column: the rate its rows are replayed '
                        'at for the live session, which times its fits by message stamps '
                        f'(default {DEFAULT_RATE_HZ:g}); a bag or a log with a time column '
                        'has its own clock')
    parser.add_argument('--full-scale', type=float, metavar='V', default=None,
                        help='refuse readings with a component at or beyond V (saturated), in '
                        'input units (default: no check)')
    parser.add_argument('--min-coverage', type=float, metavar='FRACTION',
                        default=DEFAULT_OPTIONS.min_coverage,
                        help='quality gate: share of direction cells covered, 0..1 (default '
                        f'{DEFAULT_OPTIONS.min_coverage})')
    parser.add_argument('--max-residual', type=float, metavar='PCT',
                        default=DEFAULT_OPTIONS.max_residual_pct,
                        help='quality gate: RMS of |corrected| - F in %% of F (default '
                        f'{DEFAULT_OPTIONS.max_residual_pct})')
    parser.add_argument('--columns', metavar='COLS', default=None,
                        help='text input: three zero-based field indices (e.g. 3,4,5 or 1,3,5 '
                        'for "Mx 144 My -270 Mz 415") or three header names (mx,my,mz; a '
                        'name matches "mx (uT)" too); default: detected')
    parser.add_argument('--topic', default=None,
                        help='bag input (rosbag2 or ROS 1 .bag): the MagneticField topic '
                        '(default: the only one)')
    parser.add_argument('--units', default=None,
                        help="the input's unit: uT, nT, G, mG or T (also µT, mT, gauss); "
                        '--output is converted from it to tesla. Any other word only labels '
                        "the summary (default 'input'; rosbag2 and ros2 topic echo are 'T', "
                        'a header such as "Magnetometer X (uT)" says its own)')
    parser.add_argument('--scale', type=float, metavar='TESLA_PER_COUNT', default=None,
                        help='raw counts: tesla per count (e.g. 0.15e-6 for 0.15 uT/LSB); the '
                        'samples are converted to tesla as they are read, so --output loads '
                        'right')
    fit_start.add_argument(parser)
    parser.add_argument('--output', '-o', metavar='FILE', default=None,
                        help='write the calibration YAML (ROS 2 parameters file for the node, in '
                        'tesla: needs --units or --scale unless the input says its unit) only '
                        'if the fit passes every gate')
    parser.add_argument('--plot', metavar='FILE.png', default=None,
                        help='write before/after projections and a 3-D view (also on failure); '
                        'the format follows the suffix, .png added when there is none')
    imu = parser.add_argument_group(
        "gravity and the Earth's field",
        "Align the calibration to an accelerometer (a bag's Imu topic, or logged on the same "
        'lines of a text log) from the readings held still, and check it against the World '
        'Magnetic Model at a location. Still readings are judged by the time stamps when '
        'there are any, else without a clock (consecutive rows that agree).')
    imu.add_argument('--accel', metavar='TOPIC', nargs='?', const='', default=None,
                     help='bag input: pair each reading with the sensor_msgs/Imu sample nearest '
                     'its stamp on TOPIC (default: the only Imu topic)')
    imu.add_argument('--accel-columns', metavar='COLS', default=None,
                     help="text input: the accelerometer's three zero-based field indices "
                     '(e.g. 0,1,2) or header names (ax,ay,az); the magnetometer is then '
                     '--columns or the first other numeric fields')
    imu.add_argument('--gyro-columns', metavar='COLS', default=None,
                     help="text input, with --accel-columns: the gyroscope's three fields "
                     '(indices or header names) in their unit: readings between which it '
                     'says the robot barely turned tell the own field on a drive that never '
                     'turns, as imu/data_raw does on the node')
    imu.add_argument('--gyro-units', choices=tuple(RATE_UNITS), default=None,
                     help="the unit of --gyro-columns (default: the one their header gives, "
                     "e.g. 'gx (deg/s)')")
    imu.add_argument('--max-alignment', type=float, metavar='DEG', default=None,
                     help='a larger rotation to the accelerometer is reported as a mounting '
                     'error with the remap that fixes it, not applied (default 15)')
    imu.add_argument('--latitude', type=float, metavar='DEG', default=None)
    imu.add_argument('--longitude', type=float, metavar='DEG', default=None)
    imu.add_argument('--altitude', type=float, metavar='M', default=0.0,
                     help='metres above the WGS84 ellipsoid (default 0)')
    imu.add_argument('--date', metavar='YYYY-MM-DD', default=None,
                     help='day of the recording for the model (default today)')
    imu.add_argument('--max-field-error', type=float, metavar='PCT',
                     default=MAX_FIELD_ERROR_PCT,
                     help="quality gate: fitted field vs the model's intensity (default "
                     f'{MAX_FIELD_ERROR_PCT:g} %%; needs --units)')
    imu.add_argument('--max-dip-error', type=float, metavar='DEG', default=MAX_DIP_ERROR_DEG,
                     help="quality gate: measured dip vs the model's inclination (default "
                     f'{MAX_DIP_ERROR_DEG:g}; needs --accel-columns)')
    imu.add_argument('--no-earth-gate', action='store_true',
                     help='only warn when the fit is off the model, never fail')
    own_field.add_arguments(parser)
    parser.add_argument('--json', action='store_true',
                        help='print a machine-readable summary on stdout instead of the text')
    parser.add_argument('--quiet', '-q', action='store_true',
                        help='print nothing on success (errors and failures still go out)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2, already printed)
        return int(stop.code) if isinstance(stop.code, int) else EXIT_USAGE
    try:
        with np.errstate(all='ignore'):  # results are judged (finite, gated), never warned about
            return run(args)
    except (UsageError, RecordingError, CalibrationFileError, fit_start.StartError) as error:
        _error(str(error))
        return EXIT_USAGE
    except MemoryError:
        _error(f'{args.input}: out of memory (the recording is too large for this computer; '
               'fit a part of it)')
        return EXIT_USAGE
    except KeyboardInterrupt:
        _error('interrupted')
        return EXIT_INTERRUPTED


def run(args: argparse.Namespace, stdout: TextIO | None = None) -> int:
    """Read, fit, report, write; returns the exit status."""
    out = stdout if stdout is not None else sys.stdout
    check_outputs(args)
    args = counts_in_tesla(args)
    options = fit_options(args)
    if args.all and args.k is not None:
        raise UsageError('--k sets the sample buffer; it has no effect with --all')
    settings = None if args.all else session_settings(args, options)
    progress = ProgressBar(sys.stderr, args.input)

    earth = location(args)  # usage errors before reading anything
    loaded = fit_start.read(args)
    bag = args.input != '-' and is_rosbag(Path(args.input))
    if own_field.text_options(args) if bag else own_field.bag_options(args):
        given = (own_field.text_options if bag else own_field.bag_options)(args)
        raise UsageError(f"{', '.join(given)} applies to {'text input' if bag else 'a bag'}, "
                         f"not to {'a bag' if bag else 'text'} ({args.input})")
    if args.gyro_units is not None and args.gyro_columns is None:
        raise UsageError('--gyro-units is the unit of --gyro-columns: give them together')
    if args.accel_columns is not None:
        if args.topic is not None or args.accel is not None:
            raise UsageError('--accel-columns applies to text input, not to a bag (use --accel '
                             'for its Imu topic)')
        recording = read_paired_recording(
            args.input, accel_columns=args.accel_columns, columns=args.columns,
            min_rows=options.min_samples, progress=progress.reading,
            gyro_columns=args.gyro_columns, gyro_units=args.gyro_units,
            compensation=own_field.reader_option(args, False))
    else:
        if args.gyro_columns is not None:
            raise UsageError('--gyro-columns and --gyro-units are read with --accel-columns '
                             '(a text log; a bag: --accel reads its Imu topic, gyroscope too)')
        recording = read_recording(args.input, columns=args.columns, topic=args.topic,
                                   accel_topic=args.accel, min_rows=options.min_samples,
                                   progress=progress.reading,
                                   compensation=own_field.reader_option(args, bag))
    progress.finish()
    if recording.gyro is not None and recording.stamps is None:
        raise UsageError(f'{recording.source}: --gyro-columns needs a time column: a gyroscope '
                         'is integrated over time, and --rate only replays a log without one')
    clock = Clock.of(recording, args.rate)
    units = input_units(args, recording)
    if args.scale is not None:
        recording = scaled_recording(recording, args.scale)
        units = TESLA
    per_unit = TESLA_PER_UNIT.get(units)
    full_scale_t = (None if args.full_scale is None or per_unit is None
                    else args.full_scale * (args.scale or 1.0) * per_unit)
    problem = input_problem(recording, units, args.scale is not None, full_scale_t)
    if problem is not None:
        raise UsageError(f'{recording.source}: {problem}')
    if args.output is not None and units not in TESLA_PER_UNIT:
        raise UsageError(
            f"--output writes the calibration in tesla, the node's unit, but {recording.source} "
            f"does not say its unit ('{units}'): give it with --units uT|nT|G|mG|T, or the "
            'tesla per count of raw counts with --scale (e.g. --scale 0.15e-6)')
    start = None if loaded is None else fit_start.in_units(loaded, units, recording.source)
    reference = None if earth is None else EarthReference(
        earth, units, args.max_field_error, args.max_dip_error, not args.no_earth_gate)
    metadata = {
        'units': units,
        'source': str(Path(recording.source).resolve()) if recording.source != 'stdin'
        else 'stdin',
        'mode': 'all' if settings is None else f'buffer {settings.buffer_size}',
    }
    session = learner = rates = None
    if settings is not None:
        fitted = recording.samples  # plot the whole recording, corrected by the buffer's fit
        session = learner = streamed(settings, metadata, recording, fitted, clock, earth,
                                     progress, learn_own_field=True, start=start)
        learned = own_field.learned(learner)
        if learned is not None:  # the static part from every reading without K and c
            fitted = own_field.without_own_field(recording, learned)
            session = streamed(settings, metadata, recording, fitted, clock, earth, progress,
                               start=None if start is None else fit_start.second_start(learner))
        attempt = calibrate_now(session)
        if attempt.outcome is None or attempt.outcome.result is None:
            raise UsageError(attempt.message)
        outcome = attempt.outcome
        screening = None
    else:
        fitted, screening, kept = screen_all(recording.samples, args.full_scale)
        attitudes = ups = None
        if recording.accel is not None:
            attitudes = still_attitudes(recording.samples, recording.accel, clock,
                                        args.full_scale, recording.gyro)
            ups, rates = gravity_directions(recording.accel, recording.gyro, clock.stamps_ns)
            ups = ups[kept]
        every_reading = len(fitted)
        fitted, ups = places(fitted, ups)  # each place once: the pauses weigh as the moves
        if ups is not None:
            with np.errstate(invalid='ignore', divide='ignore'):
                ups = ups / np.linalg.norm(ups, axis=1, keepdims=True)
        if earth is not None and args.field_strength is None and not args.normalise:
            intensity = earth.intensity_in(units)
            if intensity is not None:  # the model's intensity is the target, as in the node
                options = replace(options, field_strength=intensity)
        outcome = run_job(FitJob(
            'calibrate', fitted, None, None, options, metadata, attitudes=attitudes,
            alignment=alignment_settings(args).alignment_options(earth), earth=reference,
            ups=ups))
    result = outcome.result
    progress.finish()
    if session is not None:
        imu = session.report().imu
        gyro_problem, in_degrees = imu.gyro_problem, imu.gyro_in_degrees
    else:
        gyro_problem = '' if rates is None else rates.problem()
        in_degrees = rates is not None and rates.looks_like_degrees
    if gyro_problem:
        text = recording.kind == 'text'
        hint = ' (--gyro-units gives their unit)' if in_degrees and text else ''
        what = 'the gyroscope columns' if text else "the Imu messages' angular_velocity"
        recording = replace(recording, notes=(*recording.notes, f'{what}: {gyro_problem}{hint}'))

    success = result.success
    answer = None
    if start is not None:  # what the node would hold: a request adopts a passing fit
        calibration, answer = fit_start.answer(loaded, (learner, session), recording, result,
                                               options.max_residual_pct)
        success = answer['check']['fits']
        if calibration.compensation is not None:  # plotted as they were judged
            fitted = own_field.without_own_field(recording, calibration.compensation)
    else:
        calibration = own_field.with_learned(result.calibration, learner)
    if calibration is not None and units in TESLA_PER_UNIT:
        note = stated_unit_note(calibration.field_strength * TESLA_PER_UNIT[units], units)
        if note is not None:
            recording = replace(recording, notes=(*recording.notes, note))
    written = None
    if success and calibration is not None and args.output is not None:
        save_calibration(args.output, in_tesla(calibration, units), node_name=OUTPUT_SECTION)
        written = args.output
    plotted = None
    if args.plot is not None:
        plotted = write_plot(args.plot, recording, fitted, calibration, result, units,
                             success)

    summary = build_summary(args, recording, units, result, calibration, session, screening,
                            written, plotted)
    summary['compensation'] = _finite(own_field.summary(recording, calibration, learner))
    if session is None:
        summary['all'] = {'readings': every_reading, 'places': len(fitted)}
    if learner is not session and learner is not None:  # what the first pass did, learning
        counts = learner.report().counts
        summary['buffer']['learning_pass'] = {'fits': dict(counts.fits),
                                              'live_adoptions': dict(counts.adoptions)}
    alignment, earth_check = outcome.alignment, outcome.earth_check
    if answer is not None and answer['answer'] == 'in force':
        alignment, earth_check = fit_start.in_force_reference(session, calibration, reference)
    add_reference(summary, alignment, earth_check, calibration, earth, clock)
    summary['accuracy'] = accuracy_summary(calibration if success else None, answer, alignment,
                                           earth, session)
    if answer is not None:
        summary['start'] = _finite(answer)
        summary['success'] = success
        if answer['answer'] == 'in force':
            summary['field_strength_source'] = 'the calibration in force'
        summary['reason'] = (fit_start.reason(answer, options.max_residual_pct) if not success
                             else result.reason if result.success
                             else 'ok the calibration in force at the end (see answer)')
    status = EXIT_CALIBRATED if success else EXIT_FAILED_GATES
    try:
        if args.json:
            json.dump(summary, out, indent=2, allow_nan=False)
            out.write('\n')
        elif not (args.quiet and success):
            out.write(human_summary(summary))
        out.flush()
    except BrokenPipeError:
        _stop_writing(out)  # the reader (head, grep -q) has what it wanted: no traceback
    return status


def _stop_writing(out: TextIO) -> None:
    """The reader closed the pipe: send what is left in the buffer nowhere, so neither this
    write nor Python's flush at exit ends in a BrokenPipeError traceback."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, out.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # not a file descriptor (a StringIO)
        pass


# --- steps ---------------------------------------------------------------------------------


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse output names that can name no file, before any work."""
    for option, value in (('--output', args.output), ('--plot', args.plot)):
        if value is not None and not value.strip():
            raise UsageError(f'{option} needs a file name, got an empty one')


def counts_in_tesla(args: argparse.Namespace) -> argparse.Namespace:
    """--scale: the options given in counts (--field-strength, --full-scale) in tesla, as the
    samples will be; refuses a --scale that contradicts the input's stated unit."""
    if args.scale is None:
        return args
    if not (math.isfinite(args.scale) and args.scale > 0.0):
        raise UsageError(f'--scale must be a positive number of tesla per count, got '
                         f'{args.scale}')
    if args.units in TESLA_PER_UNIT:
        raise UsageError(f'--scale converts raw counts to tesla; --units {args.units} already '
                         'says the unit (give one of them)')
    if args.topic is not None:
        raise UsageError('--scale applies to raw counts in text; a rosbag2 MagneticField is in '
                         'tesla already')
    scaled = argparse.Namespace(**vars(args))
    if args.field_strength is not None:
        scaled.field_strength = args.field_strength * args.scale
    if args.full_scale is not None:
        scaled.full_scale = args.full_scale * args.scale
    return scaled


def scaled_recording(recording: Recording, tesla_per_count: float) -> Recording:
    """The recording's raw counts in tesla (--scale), refused when the input says its unit."""
    if recording.units is not None:
        raise UsageError(f"{recording.source}: the input is in '{recording.units}' "
                         f'({recording.layout}); --scale is for raw counts (drop it)')
    samples = recording.samples
    if samples.flags.writeable:
        samples *= tesla_per_count
    else:
        samples = samples * tesla_per_count
    note = f'converted to tesla: {tesla_per_count:g} T per count (--scale)'
    return replace(recording, samples=samples, units=TESLA, notes=(*recording.notes, note))


def in_tesla(calibration: Calibration, units: str) -> Calibration:
    """The calibration as the node reads it (tesla, REP-103) from the input's ``units``."""
    if units == TESLA:
        return calibration
    scaled = calibration.scaled(TESLA_PER_UNIT[units])  # b and F scale; M does not
    return scaled.with_metadata(**{UNITS_KEY: TESLA})


def fit_options(args: argparse.Namespace) -> FitOptions:
    if args.field_strength is not None and not (
            math.isfinite(args.field_strength) and args.field_strength > 0):
        raise UsageError(f'--field-strength must be a positive number, got {args.field_strength}')
    if not (math.isfinite(args.min_coverage) and 0.0 <= args.min_coverage <= 1.0):
        raise UsageError(f'--min-coverage must be a fraction 0..1, got {args.min_coverage}')
    if not (math.isfinite(args.max_residual) and args.max_residual > 0.0):
        raise UsageError(f'--max-residual must be a positive percentage, got {args.max_residual}')
    if args.full_scale is not None and not (
            math.isfinite(args.full_scale) and args.full_scale > 0):
        raise UsageError(f'--full-scale must be a positive number, got {args.full_scale}')
    strength = 1.0 if args.normalise else args.field_strength
    try:
        return FitOptions(model=args.model, field_strength=strength,
                          min_coverage=args.min_coverage, max_residual_pct=args.max_residual)
    except ValueError as error:
        raise UsageError(str(error)) from error


def location(args: argparse.Namespace) -> EarthField | None:
    """The World Magnetic Model's field at --latitude/--longitude/--altitude on --date."""
    if args.latitude is None and args.longitude is None:
        if args.date is not None:
            raise UsageError('--date needs --latitude and --longitude')
        return None
    if args.latitude is None or args.longitude is None:
        raise UsageError('give both --latitude and --longitude')
    try:
        return earth_field(args.latitude, args.longitude, args.altitude, args.date)
    except EarthFieldError as error:
        raise UsageError(str(error)) from error


def alignment_settings(args: argparse.Namespace) -> SessionSettings:
    """The alignment and model tolerances of this run (the rest: the node's defaults)."""
    defaults = SessionSettings()
    angle = defaults.max_alignment_deg if args.max_alignment is None else args.max_alignment
    settings = replace(defaults, max_alignment_deg=angle,
                       max_field_error_pct=args.max_field_error,
                       max_dip_error_deg=args.max_dip_error,
                       earth_field_gate=not args.no_earth_gate)
    problems = [problem for problem in settings.problems()
                if problem.startswith(('max_alignment', 'max_field', 'max_dip'))]
    if problems:
        raise UsageError('; '.join(problems).replace('max_', '--max-').replace('_deg', '')
                         .replace('_pct', '').replace('_', '-'))
    return settings


@dataclass(frozen=True)
class Clock:
    """When each row was taken: a bag's or a time column's stamps (``stamped``), or, for a log
    without time, rows replayed ``rate_hz`` apart for the live session's timing only."""

    stamps_ns: np.ndarray
    stamped: bool
    rate_hz: float
    source: str

    @classmethod
    def of(cls, recording: Recording, rate: float | None) -> Clock:
        """The recording's own clock; --rate only for a log without one (refused otherwise:
        two clocks would disagree)."""
        if recording.stamps is not None:
            if rate is not None:
                raise UsageError(f'--rate is for logs without time stamps; {recording.source} '
                                 f'has its own ({recording.time_source}): drop --rate')
            seconds = recording.stamps - (recording.stamps[0] if len(recording.stamps) else 0)
            step = row_step(seconds[np.isfinite(seconds)])
            measured = 1.0 / step if step > 0 else math.nan
            return cls(np.round(seconds * 1e9).astype(np.int64), True, measured,
                       str(recording.time_source))
        rate_hz = DEFAULT_RATE_HZ if rate is None else rate
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise UsageError(f'--rate must be a positive number of Hz, got {rate_hz}')
        stamps = np.round(np.arange(recording.rows) * (1e9 / rate_hz)).astype(np.int64)
        given = '--rate' if rate is not None else 'the default; --rate sets it'
        why = recording.time_source or 'none in the log'  # or a time column that is no clock
        return cls(stamps, False, rate_hz, f'{why}: rows replayed {rate_hz:g} Hz apart '
                   f'({given}) for the live session; still readings found without a clock')


def still_attitudes(samples: np.ndarray, accel: np.ndarray, clock: Clock,
                    full_scale: float | None, gyro: np.ndarray | None = None) -> np.ndarray:
    """--all: the rows' still stretches (StaticAttitudes, without a clock when the recording
    has none); rows the fit refuses (non-finite, zero, saturated) end a stretch."""
    attitudes = StaticAttitudes(clock=clock.stamped)
    span = np.ptp(samples, axis=0)
    attitudes.field_scale = float(np.mean(span)) / 2.0 or None
    times = (clock.stamps_ns * 1e-9).tolist()
    rates = [None] * len(samples) if gyro is None else gyro.tolist()
    for time_s, field, force, rate in zip(times, samples.tolist(), accel.tolist(), rates,
                                          strict=True):
        if reading_problem(*field, full_scale) is None:
            attitudes.add(time_s, field, force, rate)
        else:
            attitudes.add(time_s, (math.nan,) * 3, force, rate)
    attitudes.finish()
    return attitudes.snapshot()


def session_settings(args: argparse.Namespace, options: FitOptions) -> SessionSettings:
    """The node's defaults with this run's buffer, model and gates, in the input's units."""
    capacity = DEFAULT_CAPACITY if args.buffer is None else args.buffer
    k = DEFAULT_K if args.k is None else args.k
    if args.buffer is not None and args.buffer < 10:
        raise UsageError(f'--buffer must be at least 10, got {args.buffer}')
    if not 1 <= k < capacity:
        raise UsageError(f'--k must be between 1 and the buffer size - 1 ({capacity - 1}), '
                         f'got {k}')
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0.0):
        raise UsageError(f'--rate must be a positive number of Hz, got {args.rate}')
    return replace(
        alignment_settings(args), buffer_size=capacity, k=k, model=options.model,
        field_strength=options.field_strength or 0.0, min_coverage=options.min_coverage,
        max_residual_pct=options.max_residual_pct, full_scale=args.full_scale or 0.0,
    )


def input_units(args: argparse.Namespace, recording: Recording) -> str:
    """The input's unit: what the recording says (a bag, ros2 topic echo, a header's "(uT)"),
    else --units, else 'input' (unknown)."""
    if recording.units is not None:
        if args.units is not None and args.units != recording.units:
            raise UsageError(f"{recording.source}: the input is in '{recording.units}' "
                             f"({recording.layout}), not '{args.units}' (drop --units)")
        return recording.units
    return args.units if args.units is not None else 'input'


SANITY_ROWS = 20_000
"""Rows (evenly spread over the recording) judged for a wrong unit or a normalised field."""


def input_problem(recording: Recording, units: str, scaled: bool = False,
                  full_scale_t: float | None = None) -> str | None:
    """Why the recording cannot be calibrated (``fit/input_sanity.py``), or None: readings
    that cannot be in their stated unit (``input_units``; with ``scaled``, the tesla that
    --scale made of counts; up to --full-scale, ``full_scale_t``), or a field already
    normalised or calibrated upstream."""
    rows = recording.samples[::max(1, len(recording.samples) // SANITY_ROWS)]
    if scaled:
        fix = 'check --scale (the tesla per count: 0.15e-6 for the AK09916)'
    elif recording.units is not None:
        fix = (f'the recording says {units} ({recording.layout}), but the driver that '
               'published it used another unit: fix it there')
    else:
        fix = 'give the unit the numbers are in with --units (uT, nT, G, mG, T)'
    return field_unit_problem(rows, units, fix, full_scale_t) or normalised_problem(rows)


def streamed(settings: SessionSettings, metadata: dict[str, Any], recording: Recording,
             samples: np.ndarray, clock: Clock, earth: EarthField | None,
             progress: ProgressBar, learn_own_field: bool = False,
             start: Calibration | None = None) -> CalibrationSession:
    """A live session that has seen ``samples`` (the recording's, or them without the robot's
    own field) with the recording's clock and IMU, and with its own-field inputs when
    ``learn_own_field``; ``start`` in force from the first (as the node's calibration_file)."""
    text = recording.kind == 'text'  # a log's accelerometer may be in g or counts
    session = CalibrationSession(
        own_field.learning_settings(settings, recording) if learn_own_field else settings,
        metadata=metadata, pairing=ImuPairing(force_range=None) if text else None,
        attitudes=StaticAttitudes(clock=clock.stamped),
        input_names=recording.input_names if learn_own_field else None)
    session.set_earth_field(earth)
    if start is not None:  # once the inputs are named: where it is right depends on them
        session.apply_calibration(start, 'file')
    stream(session, samples, clock.stamps_ns, progress, recording.accel, recording.gyro,
           recording if learn_own_field else None)
    session.finish()  # the recording ends: its last still stretch too
    return session


def stream(session: CalibrationSession, samples: np.ndarray, stamps_ns: np.ndarray,
           progress: ProgressBar, accel: np.ndarray | None = None,
           gyro: np.ndarray | None = None, recording: Recording | None = None) -> None:
    """Offer every sample in order with its stamp, as the node receives messages (with its
    accelerometer row first, as imu/data_raw, when given; the ``recording``'s temperature and
    interference inputs first too, as the node's subscriptions hand them over)."""
    own = recording is not None and (recording.inputs is not None
                                     or recording.temperature is not None)
    total = len(samples)
    for start in range(0, total, PROGRESS_CHUNK):
        end = min(start + PROGRESS_CHUNK, total)
        rows = samples[start:end].tolist()
        stamps = stamps_ns[start:end].tolist()
        forces = None if accel is None else accel[start:end].tolist()
        rates = None if gyro is None else gyro[start:end].tolist()
        for index, (stamp, row) in enumerate(zip(stamps, rows, strict=True)):
            if own:
                own_field.feed(session, recording, start + index, stamp)  # type: ignore[arg-type]
            if forces is not None:
                session.process_imu(stamp, '', forces[index],
                                    None if rates is None else rates[index])
            session.process(stamp, '', row)
        session.take_events()
        progress.fitting(end, total)


SCREEN_BLOCK = 1 << 16


def screen_all(samples: np.ndarray, full_scale: float | None
               ) -> tuple[np.ndarray, dict[str, int], np.ndarray]:
    """--all: drop what the buffer would refuse outright (its own rule, reading_problem, applied
    element-wise block by block), counted by reason; the rows are not copied when none goes.
    Also returns which rows were kept."""
    problem = np.frompyfunc(reading_problem, 4, 1)
    keep = np.ones(len(samples), dtype=bool)
    counts: Counter[str] = Counter()
    for start in range(0, len(samples), SCREEN_BLOCK):
        block = samples[start:start + SCREEN_BLOCK]
        found = problem(block[:, 0], block[:, 1], block[:, 2], full_scale)
        refused = found.astype(bool)  # None (a sample) is False, a reason is True
        if refused.any():
            keep[start:start + len(block)] = ~refused
            counts.update(found[refused].tolist())
    return (samples if keep.all() else samples[keep]), dict(counts), keep


def gravity_directions(accel: np.ndarray, gyro: np.ndarray | None, stamps_ns: np.ndarray
                       ) -> tuple[np.ndarray, RateCheck]:
    """--all: gravity's unit direction behind each row as the node's pairing gives it (one
    ``GravityTracker`` over the rows in order, the gyroscope telling a tilt from the robot
    accelerating), NaN where the accelerometer is unusable or was not measuring gravity; and
    whether the gyroscope turned with the accelerometer."""
    tracker = GravityTracker()
    ups = np.full((len(accel), 3), np.nan)
    rates = [None] * len(accel) if gyro is None else gyro.tolist()
    for index, (stamp, force, rate) in enumerate(zip(stamps_ns.tolist(), accel.tolist(), rates,
                                                     strict=True)):
        if force_problem(force, None):  # NaN, Inf, zero or subnormal, as the pairing refuses
            continue
        if rate is not None and not all(math.isfinite(value) for value in rate):
            rate = None
        up = tracker.update(int(stamp), tuple(force), None if rate is None else tuple(rate))
        if up is not None:
            ups[index] = up
    return ups, tracker.rates


def write_plot(path: str, recording: Recording, fitted: np.ndarray,
               calibration: Calibration | None, result: FitResult, units: str,
               success: bool) -> str:
    from mag_calibrator_ros.tools.plotting import plot_calibration  # matplotlib: only when asked

    model = result.metrics.model if calibration is None else calibration.model
    verdict = ('calibrated' if success
               else ('NOT passing: ' + result.reason) if not result.success
               else 'NOT fitting the recording')
    title = f'{Path(recording.source).name}: {model}, {verdict}'
    if len(title) > 160:
        title = title[:157] + '...'
    outliers = result.outliers if len(result.outliers) == len(fitted) else None  # --all only
    try:
        written = plot_calibration(fitted, calibration, path, title=title, outliers=outliers,
                                   units='' if units == 'input' else units)
    except (OSError, ValueError) as error:
        raise UsageError(f'{path}: cannot write the plot ({error})') from error
    return str(written)


# --- reporting -----------------------------------------------------------------------------


def _floats(values: np.ndarray) -> list:
    return np.asarray(values, dtype=float).tolist()


def _finite(value: Any) -> Any:
    """JSON has no NaN/Inf: such metrics become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_finite(item) for item in value]
    return value


def build_summary(
    args: argparse.Namespace, recording: Recording, units: str, result: FitResult,
    calibration: Calibration | None, session: CalibrationSession | None,
    screening: dict[str, int] | None, written: str | None, plotted: str | None,
) -> dict[str, Any]:
    """Everything the run found, as plain JSON-able data (the --json output)."""
    summary: dict[str, Any] = {
        'success': bool(result.success),
        'reason': result.reason,
        'model': result.metrics.model if calibration is None else calibration.model,
        'offset': None if calibration is None else _floats(calibration.offset),
        'matrix': None if calibration is None else _floats(calibration.matrix),
        'field_strength': None if calibration is None else float(calibration.field_strength),
        'field_strength_source': ('normalised' if args.normalise else 'given'
                                  if args.field_strength is not None else 'fitted mean radius'),
        'units': units,
        'metrics': result.metrics.as_dict(),
        'gates': {'min_coverage': args.min_coverage, 'max_residual_pct': args.max_residual},
        'input': {
            'source': recording.source,
            'kind': recording.kind,
            'layout': recording.layout,
            'rows': recording.rows,
            'skipped': dict(recording.skipped),
            'notes': list(recording.notes),
            'description': recording.describe(),
        },
        'mode': 'all' if session is None else 'buffer',
        'outputs': {'calibration': written, 'plot': plotted},
    }
    if session is not None:
        live = session.report(measure_coverage=True)
        buffer, counts = live.buffer, live.counts
        summary['buffer'] = {
            'capacity': buffer.capacity,
            'k': buffer.k,
            'fill': buffer.fill,
            'seen': buffer.seen,
            'accepted': counts.accepted,
            'held_out': counts.accepted - buffer.seen,
            'readings_held': int(round(buffer.readings_held)),
            'merged': buffer.merged,
            'evicted': buffer.evicted,
            'fits': dict(counts.fits),
            'live_state': live.state,
            'live_adoptions': dict(counts.adoptions),
        }
        summary['rejects'] = dict(counts.rejects)
    else:
        summary['rejects'] = {reason: (screening or {}).get(reason, 0)
                              for reason in (*VALUE_REASONS, 'duplicate', 'magnitude_outlier')}
    return _finite(summary)


def add_reference(summary: dict[str, Any], alignment: Alignment | None,
                  earth_check: EarthCheck | None, calibration: Calibration | None,
                  earth: EarthField | None, clock: Clock) -> None:
    """The --json 'alignment' and 'earth_field' objects of the answer (when an accelerometer
    / a location was given), the calibration's rotation and the recording's clock ('time',
    'rate_hz': the stamps' median rate, or the replay rate of a log without time)."""
    summary['rotation'] = None if calibration is None else _floats(calibration.rotation.reshape(9))
    summary['rate_hz'] = _finite(float(clock.rate_hz))
    summary['time'] = {'stamped': clock.stamped, 'source': clock.source}
    if alignment is not None:
        summary['alignment'] = _finite(alignment.as_dict())
    if earth_check is not None:
        summary['earth_field'] = _finite(earth_check.as_dict())
        summary['earth_model'] = f'{earth.model} at {earth.latitude_deg:g}, ' \
                                 f'{earth.longitude_deg:g}, {earth.altitude_m:g} m, {earth.date}'


def accuracy_summary(calibration: Calibration | None, answer: dict[str, Any] | None,
                     alignment: Alignment | None, earth: EarthField | None,
                     session: CalibrationSession | None) -> dict[str, Any]:
    """The --json 'accuracy' of the answer, as the node's /diagnostics states it: the
    calibration's heading sigma by its own numbers at the dip its alignment measured (else the
    stream's, else the model's), and its status; 'uncalibrated' when it failed, 'unreliable'
    when the calibration given to start from does not fit the recording."""
    if calibration is None:
        misfit = answer is not None and not answer['check']['fits']
        told = (Accuracy('unreliable', reason=(
            'the calibration does not fit this recording: median |B| error '
            f"{answer['check']['median_error_pct']:.2f} % of F")) if misfit
            else Accuracy('uncalibrated'))
        return _finite(asdict(told))
    dip = None if alignment is None or not math.isfinite(alignment.dip_deg) \
        else alignment.dip_deg
    if dip is None and session is not None:
        live = session.report().accuracy
        dip = live.dip_deg if live.dip_source == 'stream' else None
    inclination = None if earth is None else earth.inclination_deg
    return _finite(asdict(calibration_accuracy(calibration, inclination, dip)))


def _row(values: Sequence[float]) -> str:
    return '[' + '  '.join(f'{value:>12.6g}' for value in values) + ' ]'


def human_summary(summary: dict[str, Any]) -> str:
    """The short readable report printed on stdout."""
    metrics = summary['metrics']
    source = summary['input']
    units = summary['units']
    start = summary.get('start')
    lines = ['CALIBRATED' if summary['success']
             else 'NOT CALIBRATED: the fit failed a quality gate (best-effort result below, '
                  'do not use it)' if start is None
             else 'NOT CALIBRATED: the calibration does not fit this recording (below; do not '
                  'use it)']
    label = ('not stated (give --units, or --scale for raw counts)' if units == 'input'
             else units)
    lines.append(f"input     {source['source']}: {source['rows']} rows from {source['layout']}; "
                 f'units {label}')
    skipped = describe_skips(source['skipped']) if source['skipped'] else 'none'
    lines.append(f'          skipped: {skipped}')
    lines.extend(f'          note: {note}' for note in source['notes'])
    if 'time' in summary:
        lines.append(f"time      {summary['time']['source']}")
    if summary['mode'] == 'buffer':
        info = summary['buffer']
        fits = ', '.join(f'{count} {kind}' for kind, count in info['fits'].items()) or 'none'
        lines.append(
            f"mode      buffer N={info['capacity']} k={info['k']} (as the node): "
            f"{info['accepted']} accepted ({info['held_out']} held out to judge fits), "
            f"{info['fill']} points kept standing for {info['readings_held']} readings "
            f"({info['merged']} merged as not unique); live fits: {fits}")
        if 'learning_pass' in info:
            learning = ', '.join(f'{count} {kind}' for kind, count in
                                 info['learning_pass']['fits'].items())
            lines.append(f'          that is a second pass, over the readings without the '
                         f'own field the first pass learned (its live fits: {learning})')
    else:
        lines.append(f"mode      all: every reading, one per place: {metrics['n_samples']} "
                     f"places of {summary['all']['readings']} readings")
    lines.extend(fit_start.lines(start))
    how = f"   {summary['reason'].removeprefix('ok ')}" if summary['success'] else ''
    lines.append(f"model     {summary['model']}{how}")
    if summary['offset'] is not None:
        matrix = summary['matrix']
        lines.append(f"offset b  {_row(summary['offset'])}  {units}")
        lines.append(f'matrix M  {_row(matrix[0])}')
        lines.append(f'          {_row(matrix[1])}')
        lines.append(f'          {_row(matrix[2])}')
        lines.append(f"F         {summary['field_strength']:.6g} {units} "
                     f"({summary['field_strength_source']})")
    gates = summary['gates']
    residual = metrics['residual_rms_pct']
    residual_max = metrics['residual_max_pct']
    lines.append(f'residual  {_pct(residual)} RMS of F, max {_pct(residual_max)} '
                 f"(gate {gates['max_residual_pct']:g} %)")
    hint = metrics.get('coverage_hint') or 'complete'
    coverage = None if metrics['coverage'] is None else 100.0 * metrics['coverage']
    seen = 'headings' if summary['model'] == 'planar' else 'direction sphere'
    lines.append(f'coverage  {_pct(coverage)} of the {seen} '
                 f"(gate {100.0 * gates['min_coverage']:g} %); {hint}")
    if metrics.get('unobserved'):
        unobserved = ', '.join(metrics['unobserved'])
        lines.append(f'          unobserved (held at the prior): {unobserved}')
    told = summary.get('accuracy')
    if told is not None and told['status'] != 'uncalibrated':
        lines.append('accuracy  ' + Accuracy(**told).text().removeprefix('accuracy '))
    lines.append(f"outliers  {metrics['outlier_count']} of {metrics['n_samples']} fitted points")
    rejects = {reason: count for reason, count in summary['rejects'].items() if count}
    lines.append('rejects   ' + (', '.join(f'{count} {REJECT_WORDS.get(reason, reason)}'
                                          for reason, count in rejects.items()) or 'none'))
    lines.extend(reference_lines(summary))
    lines.extend(own_field.lines(summary.get('compensation'), units))
    outputs = summary['outputs']
    if outputs['calibration']:
        lines.append(f"output    calibration written to {outputs['calibration']}")
    if outputs['plot']:
        lines.append(f"plot      {outputs['plot']}")
    if not summary['success']:
        lines.append(f"FAILED    {summary['reason']}")
        lines.append('          no calibration file written (a failed fit never writes --output)'
                     if start is None else '          no calibration file written (one '
                     'that does not fit the recording never writes --output)')
    return '\n'.join(lines) + '\n'


def reference_lines(summary: dict[str, Any]) -> list[str]:
    """The alignment and model lines of the readable report."""
    lines = []
    alignment = summary.get('alignment')
    if alignment is not None:
        if alignment['dip_deg'] is None:
            lines.append(f"alignment not determined: {alignment['reason']}")
        else:
            verdict = 'applied' if alignment['applied'] else f"NOT applied: {alignment['reason']}"
            lines.append(f"alignment rotation {alignment['angle_deg']:.2f} deg to the "
                         f"accelerometer ({verdict})")
            lines.append(f"          dip {alignment['dip_deg']:.2f} deg, scatter "
                         f"{alignment['dip_std_deg']:.2f} deg over {alignment['static_samples']}"
                         f" static attitudes ({alignment['dip_std_before_deg']:.2f} deg "
                         'unaligned)')
    earth = summary.get('earth_field')
    if earth is not None:
        intensity = ('' if earth['intensity'] is None
                     else f"{earth['intensity']:.6g} {summary['units']}, ")
        lines.append(f"earth     {summary['earth_model']}: {intensity}inclination "
                     f"{earth['inclination_deg']:.2f} deg, declination "
                     f"{earth['declination_deg']:.2f} deg")
        checks = []
        start = summary.get('start')
        field = 'field in force' if start and start['answer'] == 'in force' else 'fitted field'
        if earth['radius_ratio'] is not None:
            checks.append(f"{field} {earth['radius_ratio']:.3f}x the model's")
        else:
            checks.append('field not compared (give --units)')
        if earth['dip_error_deg'] is not None:
            checks.append(f"dip {earth['dip_error_deg']:+.2f} deg against it")
        lines.append('          ' + ', '.join(checks))
    return lines


def _pct(value: float | None) -> str:
    return 'n/a' if value is None else f'{value:.2f} %'


# --- terminal ------------------------------------------------------------------------------


class ProgressBar:
    """A one-line bar on stderr for large inputs, only on an interactive terminal.

    Never on a pipe or in CI logs (stderr not a tty, or $CI set), so --json stdout and logs stay
    clean.
    """

    WIDTH = 30

    def __init__(self, stream: TextIO, source: str) -> None:
        self.stream = stream
        self.enabled = _is_terminal(stream) and not os.environ.get('CI')
        self.large = False
        if self.enabled and source != '-':
            path = Path(source)
            self.large = path.is_file() and path.stat().st_size >= PROGRESS_MIN_BYTES
            self.large = self.large or path.is_dir() or path.suffix in ('.db3', '.mcap')
        self.shown = False

    def reading(self, done: int, total: int | None) -> None:
        if self.enabled and (self.large or done >= PROGRESS_MIN_BYTES):
            self._draw('reading', done, total)

    def fitting(self, done: int, total: int) -> None:
        if self.enabled and total >= PROGRESS_MIN_ROWS:
            self._draw('buffering', done, total)

    def _draw(self, label: str, done: int, total: int | None) -> None:
        if total:
            share = min(1.0, done / total)
            filled = int(round(self.WIDTH * share))
            bar = '#' * filled + '-' * (self.WIDTH - filled)
            self.stream.write(f'\r{label:<10} [{bar}] {100 * share:5.1f} %')
        else:
            self.stream.write(f'\r{label:<10} {done}')
        self.stream.flush()
        self.shown = True

    def finish(self) -> None:
        if self.shown:
            self.stream.write('\r' + ' ' * (self.WIDTH + 24) + '\r')
            self.stream.flush()
            self.shown = False


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def _error(message: str) -> None:
    sys.stderr.write(f'{PROG}: error: {" ".join(message.split())}\n')


if __name__ == '__main__':
    sys.exit(main())
