"""``mag_calibrator_fit``: calibrate a magnetometer offline from a recording.

The recording (text or rosbag2, see :mod:`mag_calibrator_ros.tools.recordings`) is streamed through
the calibrator node's own :class:`CalibrationSession` (sample buffer, its reference fits,
automatic calibration and refinement, at the same readings as the node) and the buffer is then
fitted as the node does on ``~/calibrate``, so an offline result predicts what the robot gets;
or, with ``--all``, every sample is fitted. The calibration is in the recording's own units.

Exit codes: 0 calibrated; 1 the fit failed a quality gate (the best-effort numbers are printed,
marked NOT passing, and no calibration file is written: a robot must never load a calibration
that failed its gates); 2 usage or input errors (one line on stderr, no traceback).
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Sequence
import json
import math
import os
from pathlib import Path
import sys
from typing import Any, NoReturn, TextIO

import numpy as np

from mag_calibrator_ros.calibration.buffer import DEFAULT_CAPACITY, DEFAULT_K
from mag_calibrator_ros.calibration.calibration import MODELS, Calibration
from mag_calibrator_ros.calibration.calibration_file import CalibrationFileError, save_calibration
from mag_calibrator_ros.calibration.fitting import FitOptions, FitResult
from mag_calibrator_ros.calibration.jobs import FitJob, run_job
from mag_calibrator_ros.calibration.screening import VALUE_REASONS, reading_problem
from mag_calibrator_ros.calibration.session import (
    CalibrationSession,
    SessionSettings,
)
from mag_calibrator_ros.tools.recordings import (
    Recording,
    RecordingError,
    describe_skips,
    read_recording,
)

PROG = 'mag_calibrator_fit'
EXIT_CALIBRATED = 0
EXIT_FAILED_GATES = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

DEFAULT_OPTIONS = FitOptions()
PROGRESS_MIN_ROWS = 20_000
"""Streaming fewer rows than this through the buffer takes well under a second: no bar."""
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
    'out_of_range': 'beyond any magnetometer (|value| > 1e12)',
    'duplicate': 'exact duplicates of a buffered sample',
    'magnitude_outlier': 'magnitude outliers',
}

EPILOG = f"""\
examples:
  {PROG} mag.txt                          fit through the node's sample buffer (default)
  {PROG} mag.txt --all --model full        fit every sample with hard + soft iron
  {PROG} log.tsv --columns 3,4,5 --output mag_calibration.yaml --plot mag.png
  {PROG} log.txt --columns 1,3,5           lines such as "Mx 144 My -270 Mz 415"
  {PROG} ~/bags/run1 --topic /imu/mag --output cal.yaml    rosbag2 (sqlite3 or mcap), tesla
  ros2 topic echo ... | {PROG} - --json    read text from stdin, machine-readable summary

field strength F (|corrected| = F): by default the fitted mean radius (magnitude kept, in input
units); --normalise makes F = 1; --field-strength F sets it (e.g. the local field from WMM in the
input's units).

exit status:
  0  calibrated (passed every quality gate; --output written)
  1  the fit failed a quality gate: the best-effort result is printed, marked NOT passing, with
     the reason (e.g. which rotation is missing); --output is NOT written (an existing file is
     left untouched) because a robot must never load a failed calibration; --plot is written
  2  usage or input error (missing/unreadable file, too few rows, bad --columns ...)
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
                      help='fit every sample instead of the buffer')
    parser.add_argument('--k', type=int, default=None,
                        help=f"neighbours in the buffer's uniqueness score (default {DEFAULT_K})")
    strength = parser.add_mutually_exclusive_group()
    strength.add_argument('--field-strength', type=float, metavar='F', default=None,
                          help='|corrected| = F in input units (default: the fitted mean radius)')
    strength.add_argument('--normalise', '--normalize', action='store_true',
                          help='F = 1 (unit-length corrected field, as mag-calibrator-rs)')
    parser.add_argument('--rate', type=float, metavar='HZ', default=DEFAULT_RATE_HZ,
                        help='sample rate of the recording: the live session times its fits by '
                        f'message stamps, replayed here at HZ (default {DEFAULT_RATE_HZ:g})')
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
                        'for "Mx 144 My -270 Mz 415") or three header names (mx,my,mz); '
                        'default: detected')
    parser.add_argument('--topic', default=None,
                        help='rosbag2 input: the MagneticField topic (default: the only one)')
    parser.add_argument('--units', default=None,
                        help="label for the input units in the output (default 'input'; "
                        "rosbag2 MagneticField is 'T')")
    parser.add_argument('--output', '-o', metavar='FILE', default=None,
                        help='write the calibration YAML (ROS 2 parameters file for the node, in '
                        'input units) only if the fit passes every gate')
    parser.add_argument('--plot', metavar='FILE.png', default=None,
                        help='write before/after projections and a 3-D view (also on failure)')
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
    except (UsageError, RecordingError, CalibrationFileError) as error:
        _error(str(error))
        return EXIT_USAGE
    except KeyboardInterrupt:
        _error('interrupted')
        return EXIT_INTERRUPTED


def run(args: argparse.Namespace, stdout: TextIO | None = None) -> int:
    """Read, fit, report, write; returns the exit status."""
    out = stdout if stdout is not None else sys.stdout
    options = fit_options(args)
    if args.all and args.k is not None:
        raise UsageError('--k sets the sample buffer; it has no effect with --all')
    settings = None if args.all else session_settings(args, options)
    progress = ProgressBar(sys.stderr, args.input)

    recording = read_recording(args.input, columns=args.columns, topic=args.topic,
                               min_rows=options.min_samples, progress=progress.reading)
    progress.finish()
    units = input_units(args, recording)
    metadata = {
        'units': units,
        'source': str(Path(recording.source).resolve()) if recording.source != 'stdin'
        else 'stdin',
        'mode': 'all' if settings is None else f'buffer {settings.buffer_size}',
    }
    session = None
    if settings is not None:
        session = CalibrationSession(settings, metadata=metadata)
        stream(session, recording.samples, args.rate, progress)
        attempt = session.calibrate_now()
        if attempt.outcome is None or attempt.outcome.result is None:
            raise UsageError(attempt.message)
        result = attempt.outcome.result
        fitted = recording.samples  # plot the whole recording, corrected by the buffer's fit
        screening = None
    else:
        fitted, screening = screen_all(recording.samples, args.full_scale)
        result = run_job(FitJob('calibrate', fitted, None, None, options, metadata)).result
    progress.finish()

    calibration = result.calibration
    written = None
    if result.success and calibration is not None and args.output:
        save_calibration(args.output, calibration, node_name=OUTPUT_SECTION)
        written = args.output
    plotted = None
    if args.plot:
        plotted = write_plot(args.plot, recording, fitted, calibration, result, units)

    summary = build_summary(args, recording, units, result, calibration, session, screening,
                            written, plotted)
    if args.json:
        json.dump(summary, out, indent=2, allow_nan=False)
        out.write('\n')
    elif not (args.quiet and result.success):
        out.write(human_summary(summary))
    return EXIT_CALIBRATED if result.success else EXIT_FAILED_GATES


# --- steps ---------------------------------------------------------------------------------


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


def session_settings(args: argparse.Namespace, options: FitOptions) -> SessionSettings:
    """The node's defaults with this run's buffer, model and gates, in the input's units."""
    capacity = DEFAULT_CAPACITY if args.buffer is None else args.buffer
    k = DEFAULT_K if args.k is None else args.k
    if args.buffer is not None and args.buffer < 10:
        raise UsageError(f'--buffer must be at least 10, got {args.buffer}')
    if not 1 <= k < capacity:
        raise UsageError(f'--k must be between 1 and the buffer size - 1 ({capacity - 1}), '
                         f'got {k}')
    if not (math.isfinite(args.rate) and args.rate > 0.0):
        raise UsageError(f'--rate must be a positive number of Hz, got {args.rate}')
    return SessionSettings(
        buffer_size=capacity, k=k, model=options.model,
        field_strength=options.field_strength or 0.0, min_coverage=options.min_coverage,
        max_residual_pct=options.max_residual_pct, full_scale=args.full_scale or 0.0,
    )


def input_units(args: argparse.Namespace, recording: Recording) -> str:
    if recording.units is not None:
        if args.units is not None and args.units != recording.units:
            raise UsageError(f'{recording.source}: a rosbag2 MagneticField is in '
                             f"'{recording.units}', not '{args.units}' (drop --units)")
        return recording.units
    return args.units if args.units is not None else 'input'


def stream(session: CalibrationSession, samples: np.ndarray, rate_hz: float,
           progress: ProgressBar) -> None:
    """Offer every sample in order, stamped at ``rate_hz``, as the node receives messages."""
    total = len(samples)
    step_ns = 1e9 / rate_hz
    for start in range(0, total, PROGRESS_CHUNK):
        session.feed(samples[start:start + PROGRESS_CHUNK], rate_hz, round(start * step_ns))
        session.take_events()
        progress.fitting(min(start + PROGRESS_CHUNK, total), total)


SCREEN_BLOCK = 1 << 16


def screen_all(samples: np.ndarray, full_scale: float | None) -> tuple[np.ndarray, dict[str, int]]:
    """--all: drop what the buffer would refuse outright (its own rule, reading_problem, applied
    element-wise block by block), counted by reason; the rows are not copied when none goes."""
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
    return (samples if keep.all() else samples[keep]), dict(counts)


def write_plot(path: str, recording: Recording, fitted: np.ndarray,
               calibration: Calibration | None, result: FitResult, units: str) -> str:
    from mag_calibrator_ros.tools.plotting import plot_calibration  # matplotlib: only when asked

    verdict = 'calibrated' if result.success else 'NOT passing: ' + result.reason
    title = f'{Path(recording.source).name}: {result.metrics.model}, {verdict}'
    if len(title) > 160:
        title = title[:157] + '...'
    outliers = result.outliers if len(result.outliers) == len(fitted) else None  # --all only
    try:
        plot_calibration(fitted, calibration, path, title=title, outliers=outliers,
                         units='' if units == 'input' else units)
    except (OSError, ValueError) as error:
        raise UsageError(f'{path}: cannot write the plot ({error})') from error
    return path


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
        buffer = session.buffer
        summary['buffer'] = {
            'capacity': buffer.capacity,
            'k': buffer.k,
            'fill': buffer.fill,
            'seen': buffer.seen,
            'accepted': session.accepted,
            'held_out': session.accepted - buffer.seen,
            'readings_held': int(round(float(np.sum(buffer.counts)))),
            'merged': buffer.merged,
            'evicted': buffer.evicted,
            'fits': dict(session.jobs_run),
            'live_state': session.state,
            'live_adoptions': dict(session.adoptions),
        }
        summary['rejects'] = session.rejects()
    else:
        summary['rejects'] = {reason: (screening or {}).get(reason, 0)
                              for reason in (*VALUE_REASONS, 'duplicate', 'magnitude_outlier')}
    return _finite(summary)


def _row(values: Sequence[float]) -> str:
    return '[' + '  '.join(f'{value:>12.6g}' for value in values) + ' ]'


def human_summary(summary: dict[str, Any]) -> str:
    """The short readable report printed on stdout."""
    metrics = summary['metrics']
    source = summary['input']
    units = summary['units']
    lines = ['CALIBRATED' if summary['success']
             else 'NOT CALIBRATED: the fit failed a quality gate (best-effort result below, '
                  'do not use it)']
    label = 'not stated (label them with --units)' if units == 'input' else units
    lines.append(f"input     {source['source']}: {source['rows']} rows from {source['layout']}; "
                 f'units {label}')
    skipped = describe_skips(source['skipped']) if source['skipped'] else 'none'
    lines.append(f'          skipped: {skipped}')
    lines.extend(f'          note: {note}' for note in source['notes'])
    if summary['mode'] == 'buffer':
        info = summary['buffer']
        fits = ', '.join(f'{count} {kind}' for kind, count in info['fits'].items()) or 'none'
        lines.append(
            f"mode      buffer N={info['capacity']} k={info['k']} (as the node): "
            f"{info['accepted']} accepted ({info['held_out']} held out to judge fits), "
            f"{info['fill']} points kept standing for {info['readings_held']} readings "
            f"({info['merged']} merged as not unique); live fits: {fits}")
    else:
        lines.append(f"mode      all: fitted every one of {metrics['n_samples']} samples")
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
    lines.append(f'coverage  {_pct(coverage)} of the direction sphere '
                 f"(gate {100.0 * gates['min_coverage']:g} %); {hint}")
    if metrics.get('unobserved'):
        unobserved = ', '.join(metrics['unobserved'])
        lines.append(f'          unobserved (held at the prior): {unobserved}')
    lines.append(f"outliers  {metrics['outlier_count']} of {metrics['n_samples']} fitted points")
    rejects = {reason: count for reason, count in summary['rejects'].items() if count}
    lines.append('rejects   ' + (', '.join(f'{count} {REJECT_WORDS.get(reason, reason)}'
                                          for reason, count in rejects.items()) or 'none'))
    outputs = summary['outputs']
    if outputs['calibration']:
        lines.append(f"output    calibration written to {outputs['calibration']}")
    if outputs['plot']:
        lines.append(f"plot      {outputs['plot']}")
    if not summary['success']:
        lines.append(f"FAILED    {summary['reason']}")
        lines.append('          no calibration file written (a failed fit never writes --output)')
    return '\n'.join(lines) + '\n'


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
