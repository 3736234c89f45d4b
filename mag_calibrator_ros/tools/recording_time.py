# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""A text log's time column, and the unit its stamps are in (seconds, ms, us, ns)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import re

import numpy as np

from mag_calibrator_ros.calibration.live.screening import MAX_FORWARD_JUMP_NS
from mag_calibrator_ros.tools.recording_columns import _UNITS, _data_pattern, _header_cells
from mag_calibrator_ros.tools.recording_lines import LAYOUT_SAMPLE_LINES


@dataclass(frozen=True)
class TimeColumn:
    """A time column a header names: its field, its name and the unit its header gives."""

    index: int
    name: str
    header_unit: str | None


TIME_NAMES = frozenset({'time', 't', 'stamp', 'timestamp', 'time_stamp', 'ts', 'millis',
                        'elapsed', 'elapsed_time', 'time_elapsed', 'seconds', 'secs',
                        'header_stamp', 'field_header_stamp'})
"""Header names of a time column (units in brackets or as a suffix _s, _ms, _us, _ns dropped;
``%time`` of ``rostopic echo -p`` is 'time')."""
TIME_UNITS = {'s': 1.0, 'sec': 1.0, 'secs': 1.0, 'seconds': 1.0, 'ms': 1e-3, 'msec': 1e-3,
              'millis': 1e-3, 'milliseconds': 1e-3, 'us': 1e-6, '\u00b5s': 1e-6,
              'microseconds': 1e-6, 'ns': 1e-9, 'nanoseconds': 1e-9}
"""Seconds per unit of the time units a header may give."""
_TIME_UNIT_WORDS = {1.0: 'seconds', 1e-3: 'milliseconds', 1e-6: 'microseconds',
                    1e-9: 'nanoseconds'}


def _time_name(cell: str) -> tuple[str, str | None]:
    """(the name without units, the unit the cell gives or None): 'Time (ms)' -> ('time',
    'ms'), 'time_ms' -> ('time', 'ms'), 'millis' -> ('millis', 'ms')."""
    bracketed = _UNITS.findall(cell)
    unit = bracketed[0][1:-1].strip().lower() if len(bracketed) == 1 else None
    name = '_'.join(re.findall(r'[a-z0-9]+', _UNITS.sub(' ', cell).lower()))
    base, _, suffix = name.rpartition('_')
    if unit is None and base and suffix in TIME_UNITS and base in TIME_NAMES:
        name, unit = base, suffix
    if unit is None and name == 'millis':
        unit = 'ms'
    return name, unit


def time_column(lines: list[str], taken: Sequence[int]) -> TimeColumn | None:
    """The time column the header before the data names (one cell of TIME_NAMES, a number on
    the data lines, not one of the ``taken`` fields); None when there is none or several."""
    found = _data_pattern(lines)
    if found is None:
        return None
    field_count, numeric, position = found
    for line in reversed(lines[:position]):
        if not line.strip():
            continue
        cells = _header_cells(line, field_count)
        if cells is None:
            return None
        hits = []
        for index, cell in enumerate(cells):
            name, unit = _time_name(cell)
            if unit in CELSIUS_UNITS:
                continue  # 'T (C)' is a temperature
            if name in TIME_NAMES and index in numeric and index not in taken:
                hits.append(TimeColumn(index, cell.strip(), unit))
        return hits[0] if len(hits) == 1 else None
    return None


CELSIUS_UNITS = frozenset({'c', '\u00b0c', 'degc', 'deg c', 'celsius'})
KELVIN_UNITS = frozenset({'k', 'kelvin'})
FAHRENHEIT_UNITS = frozenset({'f', '\u00b0f', 'degf', 'deg f', 'fahrenheit'})

MAX_STEP_S = 1.5
"""Elapsed-time stamps whose steps would be longer than this in milliseconds (under one reading
in 1.5 s) are microseconds, longer still nanoseconds: PX4's ``ulog2csv`` 'timestamp' steps 4000
to 20000 at 250 to 50 Hz, an Arduino's micros() alike, while a 1 Hz millis() log with jitter
(1001, 1002 ...) stays milliseconds."""
EPOCH_SECONDS = (946_684_800.0, 4_102_444_800.0)
"""Stamps since 1970 are dates from 2000 to 2100: PX4's 1.1e8 microseconds since boot are not
seconds of 1973."""


def time_unit(values: np.ndarray, header_unit: str | None = None) -> tuple[float, str]:
    """(seconds per unit, why) of a time column: the header's unit when it gives one; else
    from the values: numbers that are dates (EPOCH_SECONDS) in s, ms, us or ns since 1970 whose
    steps are not jumps the calibrator refuses (MAX_FORWARD_JUMP_NS), and elapsed time by its
    steps: integer steps of a millisecond or more are milliseconds (an Arduino's millis()), as
    are steps of 5 or more (no log has 5 s between readings and calls it a calibration), up to
    MAX_STEP_S; anything else is seconds."""
    if header_unit is not None and header_unit in TIME_UNITS:
        scale = TIME_UNITS[header_unit]
        return scale, f'{_TIME_UNIT_WORDS[scale]} (from the header)'
    finite = values[np.isfinite(values)]
    if len(finite) < 2:
        return 1.0, 'seconds (too few values to tell)'
    step = row_step(finite)
    size = float(np.median(np.abs(finite)))
    for scale in (1e-9, 1e-6, 1e-3, 1.0):
        if (EPOCH_SECONDS[0] <= size * scale < EPOCH_SECONDS[1]
                and step * scale * 1e9 <= MAX_FORWARD_JUMP_NS):
            return scale, f'{_TIME_UNIT_WORDS[scale]} since 1970 (from their size)'
    integers = bool(np.all(finite == np.round(finite)))
    if step * 1e-3 > MAX_STEP_S:
        scale = 1e-6 if step * 1e-6 <= MAX_STEP_S else 1e-9
        return scale, (f'{_TIME_UNIT_WORDS[scale]} (from steps of {step:g}: a '
                       f'{1.0 / (step * scale):.3g} Hz log)')
    if step >= 5.0 or (integers and step >= 1.0):
        return 1e-3, f'milliseconds (from steps of {step:g}: a {1000.0 / step:.3g} Hz log)'
    rate = f': a {1.0 / step:.3g} Hz log' if step > 0 else ''
    return 1.0, f'seconds (from steps of {step:g}{rate})'


def row_step(values: np.ndarray) -> float:
    """The time between rows of finite stamps: the median forward step, or, when most rows
    repeat the previous stamp (a clock coarser than the rows: whole seconds at 100 Hz, read as
    a 1 kHz millis() log by their steps of 1), the forward span over the rows."""
    steps = np.diff(values)
    forward = steps[steps > 0]
    if not len(forward):
        return 0.0
    if np.count_nonzero(steps == 0) > len(steps) / 2:
        return float(forward.sum()) / len(steps)
    return float(np.median(forward))


MAX_BACKWARD_SHARE = 0.01
"""A time column is the recording's clock when no more than this share of its steps go back (a
wrap or a restart now and then); a column named 'time' whose values are in no order is none,
and the calibrator refused 98 % of its rows as stamps going back (issue #47)."""


def _stamps(table: np.ndarray, time: TimeColumn | None) -> tuple[np.ndarray | None, str | None]:
    """Seconds of each row from the time column read as the table's last column, with what it
    is; no stamps, and why, when the column is no clock (MAX_BACKWARD_SHARE)."""
    if time is None:
        return None, None
    column, source = table[:, -1], f"column '{time.name}' (field {time.index})"
    steps = np.diff(column[np.isfinite(column)])
    backward = int(np.count_nonzero(steps < 0))
    if backward > MAX_BACKWARD_SHARE * len(steps):
        return None, (f'{source} is no clock ({100.0 * backward / len(steps):.0f} % of its '
                      'steps go back), not used')
    scale, why = time_unit(column[:LAYOUT_SAMPLE_LINES], time.header_unit)
    return column * scale, f'{source}, {why}'
