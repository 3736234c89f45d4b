# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Read a text recording into a ``Recording``: columns, ``ros2 topic echo``, an IMU beside."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import replace
import itertools
import math
from pathlib import Path
import sys
from typing import TextIO
import warnings

import numpy as np

from mag_calibrator_ros.calibration.live.screening import MAX_READING
from mag_calibrator_ros.tools.recording_bags import is_rosbag
from mag_calibrator_ros.tools.recording_columns import (
    _INDEX,
    _UNITS,
    TextLayout,
    _data_pattern,
    _explicit_layout,
    detect_layout,
)
from mag_calibrator_ros.tools.recording_inputs import (
    InputColumns,
    _compensation_extras,
    _header_before_data,
    compensation_columns,
)
from mag_calibrator_ros.tools.recording_lines import (
    BLOCK_LINES,
    STDIN,
    _blocks,
    _bounded_lines,
    _decimal_comma,
    _decimal_point,
    _GrowingRows,
    _head,
    _is_comment,
    _is_text,
    _number,
    _refuse_binary,
    _split,
)
from mag_calibrator_ros.tools.recording_time import _stamps, time_column
from mag_calibrator_ros.tools.recording_value import ProgressCallback, Recording, RecordingError


def read_text_file(
    path: Path, *, columns: str | None = None, progress: ProgressCallback | None = None,
    compensation: tuple[str | None, str | None] | None = None,
) -> Recording:
    """Read a text recording from a file (see the module docstring for the formats)."""
    if not path.exists():
        raise RecordingError(f'{path}: no such file')
    try:
        with path.open('rb') as probe:
            head = probe.read(4096)
        total = path.stat().st_size
        _refuse_binary(path, head)
        with path.open(encoding='utf-8-sig', errors='replace', newline=None) as stream:
            return _read_lines(_bounded_lines(stream, str(path)), str(path), columns, progress,
                               total, compensation)
    except OSError as error:
        raise RecordingError(f'{path}: cannot read ({error.strerror or error})') from error


def read_text(
    stream: TextIO, source: str = 'stdin', *, columns: str | None = None,
    progress: ProgressCallback | None = None,
    compensation: tuple[str | None, str | None] | None = None,
) -> Recording:
    """Read a text recording from an open text stream (stdin, a StringIO ...)."""
    try:
        return _read_lines(_bounded_lines(stream, source), source, columns, progress, None,
                           compensation)
    except UnicodeDecodeError as error:
        raise RecordingError(f'{source}: not text ({error.reason})') from error


def _read_lines(
    stream: Iterable[str], source: str, columns: str | None,
    progress: ProgressCallback | None, total: int | None,
    compensation: tuple[str | None, str | None] | None = None,
) -> Recording:
    lines = iter(stream)
    first = _head(lines)
    if _is_topic_echo(first):
        if columns is not None:
            raise RecordingError(f'{source}: --columns applies to column text, not to the '
                                 'messages of ros2 topic echo (read as magnetic_field x, y, z)')
        return _read_topic_echo(itertools.chain(first, lines), source, progress, total)
    notes: tuple[str, ...] = ()
    if _decimal_comma(first):
        first = [_decimal_point(line) for line in first]
        lines = map(_decimal_point, lines)
        notes = ('";"-separated numbers with decimal commas',)
    if columns is not None:
        layout = _explicit_layout(columns, first, source)
    elif not any(line.strip() for line in first):
        raise RecordingError(f'{source}: empty (no data lines)')
    else:
        layout = detect_layout(first, source)
    time = time_column(first, layout.indices)
    if time is not None:
        layout = replace(layout, time_index=time.index)
    chosen = InputColumns()
    if compensation is not None:
        taken = (*layout.indices, *(() if time is None else (time.index,)))
        chosen = compensation_columns(first, taken, source, *compensation)
        layout = replace(layout, extra=chosen.fields)
    table, skipped = _parse(itertools.chain(first, lines), layout, progress, total)
    stamps, time_source = _stamps(table, time)
    extras = _compensation_extras(table, chosen)
    return Recording(table[:, :3].copy() if time is not None or chosen.fields else table[:, :3],
                     source, 'text', layout.description, skipped, layout.units,
                     (*notes, *layout.notes), stamps=stamps, time_source=time_source, **extras)


def _parse(
    lines: Iterator[str], layout: TextLayout, progress: ProgressCallback | None, total: int | None,
) -> tuple[np.ndarray, dict[str, int]]:
    """Every line, a block at a time (_blocks): numpy reads a block of plain numeric lines at
    once, any other block goes line by line (with the same result, see _parse_block). Rows:
    x, y, z and the time when the layout has one."""
    rows = _GrowingRows(len(layout.fields))
    skipped: Counter[str] = Counter()
    consumed = 0
    any_block = False
    for block in _blocks(lines):
        any_block = True
        block_rows, block_skipped = _parse_block(block, layout, len(rows) > 0)
        rows.extend(block_rows)
        skipped.update(block_skipped)
        consumed += sum(map(len, block))
        if progress is not None:
            progress(consumed, total)
    if progress is not None and not any_block:
        progress(consumed, total if total is not None else consumed)
    return rows.result(), {reason: count for reason, count in skipped.items() if count}


def _parse_block(
    block: list[str], layout: TextLayout, seen_rows: bool
) -> tuple[np.ndarray, Counter[str]]:
    """(rows (m, 3), skips) of one block of lines. A block of plain numeric lines with the
    layout's delimiter and field count is converted by numpy in one call; numpy refuses
    anything else (text, missing or extra fields, comments), and such a block is parsed line by
    line instead, so both give the same rows and the same counts."""
    if layout.numpy_fields is not None and max(layout.fields) < layout.numpy_fields:
        try:
            with warnings.catch_warnings():  # a block of blank lines is no news
                warnings.simplefilter('ignore', UserWarning)
                table = np.loadtxt(block, delimiter=layout.delimiter, dtype=np.float64,
                                   ndmin=2, comments=None, quotechar='"')
        except ValueError:
            table = None
        if table is not None and table.shape[1] == layout.numpy_fields:
            return _screen_rows(table[:, list(layout.fields)], layout.time_index is not None)
    return _parse_lines(block, layout, seen_rows)


def _screen_rows(rows: np.ndarray, timed: bool = False) -> tuple[np.ndarray, Counter[str]]:
    """Drop rows with a NaN/Inf or a value beyond MAX_READING in x, y, z, or (``timed``) a time
    (the last column) that is no finite number, counted."""
    skipped: Counter[str] = Counter()
    finite = np.all(np.isfinite(rows[:, :3]), axis=1)
    keep = np.all(np.abs(rows[:, :3]) <= MAX_READING, axis=1)  # False for NaN too
    skipped['non_finite'] = int(np.count_nonzero(~finite))
    skipped['out_of_range'] = int(np.count_nonzero(finite & ~keep))
    if timed:
        stamped = np.isfinite(rows[:, -1])
        skipped['bad_time'] = int(np.count_nonzero(keep & ~stamped))
        keep &= stamped
    return (rows if keep.all() else rows[keep]), skipped


def _parse_lines(
    block: list[str], layout: TextLayout, seen_rows: bool
) -> tuple[np.ndarray, Counter[str]]:
    rows: list[tuple[float, ...]] = []
    skipped: Counter[str] = Counter()
    needed = max(layout.fields) + 1
    for line in block:
        tokens = _data_tokens(line, skipped)
        if tokens is None:
            continue
        reason, row = _parse_line(tokens, layout, needed)
        if row is not None:
            rows.append(row)
        else:
            _count_skipped(skipped, tokens, reason, before_data=not (seen_rows or rows))
    return np.array(rows, dtype=np.float64).reshape(-1, len(layout.fields)), skipped


def _data_tokens(line: str, skipped: Counter[str]) -> list[str] | None:
    """The fields of a line that may hold data; None for a blank line or a comment (counted)."""
    if not line.strip():
        return None
    if _is_comment(line):
        skipped['comment'] += 1
        return None
    return _split(line)


def _count_skipped(skipped: Counter[str], tokens: list[str], reason: str, before_data: bool
                   ) -> None:
    """A line that gave no row: a header when text comes before any data, else ``reason``."""
    skipped['header' if before_data and _is_text(tokens) else reason] += 1


def _parse_line(
    tokens: list[str], layout: TextLayout, needed: int,
) -> tuple[str, tuple[float, ...] | None]:
    """(why not, None) or ('', (x, y, z[, time])) of one line's fields."""
    if layout.field_count is not None and len(tokens) != layout.field_count:
        return 'wrong_field_count', None
    if len(tokens) < needed:
        return 'too_few_fields', None
    values = [_number(tokens[i]) for i in layout.fields]
    for position in range(3, 3 + len(layout.extra)):
        if values[position] is None:
            values[position] = math.nan  # an input's garbage: counted by compensation_inputs
    if any(value is None for value in values[:3]):
        return 'not_numeric', None
    x, y, z = values[:3]
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return 'non_finite', None
    if max(abs(x), abs(y), abs(z)) > MAX_READING:
        return 'out_of_range', None
    if layout.time_index is not None and (values[-1] is None or not math.isfinite(values[-1])):
        return 'bad_time', None
    return '', tuple(values)  # type: ignore[arg-type]


# --- ros2 topic echo (YAML messages) ---------------------------------------------------------

_ECHO_FIELD = 'magnetic_field:'
_ECHO_SEPARATOR = '---'
_YAML_SPECIAL = {'.nan': 'nan', '.inf': 'inf', '+.inf': 'inf', '-.inf': '-inf'}


def _is_topic_echo(lines: list[str]) -> bool:
    """``ros2 topic echo`` of a MagneticField: a top-level ``magnetic_field:`` key and ``---``
    between messages."""
    stripped = [line.rstrip() for line in lines]
    return _ECHO_FIELD in stripped and _ECHO_SEPARATOR in stripped


def _read_topic_echo(
    lines: Iterator[str], source: str, progress: ProgressCallback | None, total: int | None,
) -> Recording:
    """``magnetic_field`` x, y, z of every message ``ros2 topic echo`` printed (tesla, REP-103):
    a message missing one is counted as incomplete, never guessed."""
    rows = _GrowingRows(3)
    pending: list[tuple[float, float, float]] = []
    skipped: Counter[str] = Counter()
    values: dict[str, float | None] = {}
    in_field = False
    started = False
    consumed = 0

    def finish() -> None:
        if started or values:
            row = tuple(values.get(axis) for axis in 'xyz')
            if any(axis not in values for axis in 'xyz'):
                skipped['incomplete'] += 1
            elif any(value is None for value in row):
                skipped['not_numeric'] += 1
            else:
                pending.append(row)  # type: ignore[arg-type]
        values.clear()

    for line in lines:
        consumed += len(line)
        text = line.rstrip()
        if not text:
            continue
        if not text[0].isspace():  # a top-level key (or the separator) ends the field's block
            in_field = text == _ECHO_FIELD
            if text == _ECHO_SEPARATOR:
                finish()
                started = False
            else:
                started = True
        elif in_field:
            key, _, value = text.strip().partition(':')
            if key in ('x', 'y', 'z'):
                value = value.strip().strip('"\'')
                values[key] = _number(_YAML_SPECIAL.get(value.lower(), value))
        if len(pending) >= BLOCK_LINES:
            _add_screened(rows, pending, skipped)
            if progress is not None:
                progress(consumed, total)
    finish()
    _add_screened(rows, pending, skipped)
    if progress is not None:
        progress(consumed, total if total is not None else consumed)
    return Recording(rows.result(), source, 'text', 'ros2 topic echo messages (magnetic_field)',
                     {reason: count for reason, count in skipped.items() if count}, 'T')


def _add_screened(rows: _GrowingRows, pending: list[tuple[float, float, float]],
                  skipped: Counter[str]) -> None:
    """Move a block of values into ``rows``, NaN/Inf and out-of-range rows dropped, counted."""
    kept, block_skipped = _screen_rows(np.array(pending, dtype=np.float64).reshape(-1, 3))
    rows.extend(kept)
    skipped.update(block_skipped)
    pending.clear()


# --- magnetometer and accelerometer on one line (alignment to the IMU) -----------------------


def read_paired_recording(
    source: str | Path,
    *,
    accel_columns: str,
    columns: str | None = None,
    min_rows: int = 1,
    stdin: TextIO | None = None,
    progress: ProgressCallback | None = None,
    gyro_columns: str | None = None,
    gyro_units: str | None = None,
    compensation: tuple[str | None, str | None] | None = None,
) -> Recording:
    """A text recording that logs the accelerometer beside the magnetometer on each line.

    ``accel_columns``: three zero-based field indices or header names (``'0,1,2'``,
    ``'ax,ay,az'``); ``columns`` the magnetometer's, by default the first three numeric fields
    that are not the accelerometer's. A line is used only when all six values are numbers, so
    ``Recording.samples`` and ``Recording.accel`` stay row for row. ``gyro_columns``: the
    gyroscope's three fields in ``gyro_units`` (RATE_UNITS), else in the unit their header
    gives (``gx (deg/s)``), converted to rad/s (NaN where a value is no number);
    ``compensation``: the own field's inputs too, as ``read_recording`` reads them.
    """
    options = (gyro_columns, gyro_units, compensation)
    if str(source) == STDIN:
        stream = stdin if stdin is not None else sys.stdin
        return _read_paired(_bounded_lines(stream, 'stdin'), 'stdin', accel_columns, columns,
                            min_rows, progress, None, *options)
    path = Path(source)
    if is_rosbag(path):
        raise RecordingError(f'{path}: --accel-columns applies to text input, not to a rosbag2 '
                             'bag')
    if not path.exists():
        raise RecordingError(f'{path}: no such file')
    try:
        with path.open('rb') as probe:
            head = probe.read(4096)
        _refuse_binary(path, head)
        with path.open(encoding='utf-8-sig', errors='replace', newline=None) as stream:
            return _read_paired(_bounded_lines(stream, str(path)), str(path), accel_columns,
                                columns, min_rows, progress, path.stat().st_size, *options)
    except OSError as error:
        raise RecordingError(f'{path}: cannot read ({error.strerror or error})') from error


def _read_paired(stream: Iterable[str], source: str, accel_columns: str, columns: str | None,
                 min_rows: int, progress: ProgressCallback | None, total: int | None,
                 gyro_columns: str | None = None, gyro_units: str | None = None,
                 compensation: tuple[str | None, str | None] | None = None) -> Recording:
    lines = iter(stream)
    first = _head(lines)
    notes: tuple[str, ...] = ()
    if _decimal_comma(first):
        first = [_decimal_point(line) for line in first]
        lines = map(_decimal_point, lines)
        notes = ('";"-separated numbers with decimal commas',)
    accel = _explicit_layout(accel_columns, first, source, '--accel-columns')
    gyro = (None if gyro_columns is None
            else _explicit_layout(gyro_columns, first, source, '--gyro-columns'))
    beside = (*accel.indices, *(() if gyro is None else gyro.indices))
    if columns is not None:
        mag = _explicit_layout(columns, first, source)
    else:
        try:  # a header naming the magnetometer's columns
            mag = detect_layout(first, source, 'magnetometer', guess=False, read_beside=beside)
            notes += mag.notes
        except RecordingError:
            mag = _other_numeric_fields(first, beside, source)
            notes += (f'magnetometer from {mag.description}, the first numeric fields besides '
                      f"the {'accelerometer' if gyro is None else 'IMU'} (choose others with "
                      '--columns)',)
    sensors = [('magnetometer', mag), ('accelerometer', accel), ('gyroscope', gyro)]
    for number, (name, layout) in enumerate(sensors):
        for other, other_layout in sensors[number + 1:]:
            if layout is not None and other_layout is not None and (
                    set(layout.indices) & set(other_layout.indices)):
                raise RecordingError(f'{source}: the {name} fields {layout.description} overlap '
                                     f'the {other} fields {other_layout.description}')
    gyro_fields = () if gyro is None else gyro.indices
    time = time_column(first, (*mag.indices, *accel.indices, *gyro_fields))
    time_fields = () if time is None else (time.index,)
    chosen = InputColumns()
    if compensation is not None:
        chosen = compensation_columns(first, (*mag.indices, *accel.indices, *gyro_fields,
                                              *time_fields), source, *compensation)
    needed = max(*mag.indices, *accel.indices, *gyro_fields, *chosen.fields, *time_fields) + 1
    found = _data_pattern(first)
    field_count = None if found is None else found[0]
    units = mag.units
    mag = TextLayout(mag.indices, field_count, mag.description,
                     time_index=None if time is None else time.index,
                     extra=(*gyro_fields, *chosen.fields))
    accel_layout = TextLayout(accel.indices, field_count, accel.description)
    rows = _GrowingRows(len(mag.fields) + 3)
    skipped: Counter[str] = Counter()
    consumed = 0
    for block in _blocks(itertools.chain(first, lines)):
        block_rows: list[tuple[float, ...]] = []
        for line in block:
            consumed += len(line)
            tokens = _data_tokens(line, skipped)
            if tokens is None:
                continue
            reason, field = _parse_line(tokens, mag, needed)
            specific_force = None
            if field is not None:
                reason, specific_force = _parse_line(tokens, accel_layout, needed)
            if field is not None and specific_force is not None:
                block_rows.append((*field[:3], *specific_force, *field[3:]))
            else:
                _count_skipped(skipped, tokens, reason,
                               before_data=not (block_rows or len(rows)))
        rows.extend(block_rows)
        if progress is not None:
            progress(consumed, total)
    if progress is not None:
        progress(consumed, total if total is not None else consumed)
    data = rows.result()
    layout = f'{mag.description}; accelerometer {accel.description}' + (
        '' if gyro is None else f'; gyroscope {gyro.description}')
    if len(data) < max(min_rows, 1):
        found_rows = 'no usable rows' if len(data) == 0 else f'only {len(data)} usable rows'
        need = f' (need at least {min_rows})' if min_rows > 1 else ''
        raise RecordingError(f'{source}: {found_rows} from {layout}{need}')
    stamps, time_source = _stamps(data, time)
    rates = None if gyro is None else data[:, 6:9] * RATE_UNITS[
        _rate_unit(first, gyro, gyro_units, source)]
    if rates is not None and not np.isfinite(rates).all():
        bad = int(np.count_nonzero(~np.isfinite(rates).all(axis=1)))
        notes += (f'gyroscope {gyro.description}: {bad} of {len(rates)} rows not a finite '  # type: ignore[union-attr]
                  'number (each ends a stretch of integrated attitude)',)
    extras = _compensation_extras(data[:, [0, 1, 2, *range(6 + len(gyro_fields),
                                                            data.shape[1])]], chosen)
    return Recording(data[:, :3].copy(), source, 'text', layout, dict(skipped), units, notes,
                     accel=data[:, 3:6].copy(), gyro=rates, stamps=stamps,
                     time_source=time_source, **extras)


RATE_UNITS = {'rad/s': 1.0, 'deg/s': math.pi / 180.0}
"""A gyroscope's units: rad/s per unit."""
_RATE_WORDS = {'rad/s': 'rad/s', 'rad/sec': 'rad/s', 'rads': 'rad/s', 'deg/s': 'deg/s',
               'deg/sec': 'deg/s', 'dps': 'deg/s', '\u00b0/s': 'deg/s'}


def _rate_unit(lines: list[str], gyro: TextLayout, given: str | None, source: str) -> str:
    """The gyroscope's unit: ``given`` (--gyro-units), which its header must not contradict,
    else the one its header gives all three columns (``gx (deg/s)``); raises RecordingError
    when neither says."""
    header = _header_before_data(lines)
    said = None
    if header is not None and max(gyro.indices) < len(header[0]):
        words = set()
        for index in gyro.indices:
            bracketed = [unit[1:-1].strip().lower() for unit in _UNITS.findall(header[0][index])
                         if not _INDEX.fullmatch(unit)]
            words.add(_RATE_WORDS.get(bracketed[0]) if len(bracketed) == 1 else None)
        said = words.pop() if len(words) == 1 else None
    if given is not None and said is not None and given != said:
        raise RecordingError(f'{source}: the gyroscope columns {gyro.description} say {said}, '
                             f'not {given} (drop --gyro-units)')
    unit = given or said
    if unit is None:
        raise RecordingError(f'{source}: the gyroscope columns {gyro.description} do not say '
                             'their unit: give --gyro-units rad/s or deg/s')
    return unit


def _other_numeric_fields(lines: list[str], taken: tuple[int, ...], source: str) -> TextLayout:
    """The first three numeric fields of the most common data line that are not in ``taken``."""
    found = _data_pattern(lines)
    free = [] if found is None else [index for index in found[1] if index not in taken][:3]
    if len(free) < 3:
        raise RecordingError(f'{source}: no three numeric fields besides the accelerometer '
                             f'fields {",".join(map(str, taken))} in the first {len(lines)} '
                             'lines; give --columns')
    return TextLayout((free[0], free[1], free[2]), None, f'fields {",".join(map(str, free))}')
