# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field's inputs in a text log (current, temperature), and their bad values."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math
import re

import numpy as np

from mag_calibrator_ros.tools.recording_columns import _data_pattern, _header_cells, field_named
from mag_calibrator_ros.tools.recording_time import (
    CELSIUS_UNITS,
    FAHRENHEIT_UNITS,
    KELVIN_UNITS,
    _time_name,
)
from mag_calibrator_ros.tools.recording_value import RecordingError

CURRENT_NAMES = frozenset({'current', 'battery_current', 'motor_current', 'bus_current',
                           'current_a', 'amps', 'amperes', 'ibat', 'i_bat'})
"""Header names of an interference input's column (units in brackets dropped; any name ending
in ``_current`` too): the current the robot's motors and battery draw."""
TEMPERATURE_NAMES = frozenset({'temperature', 'temp', 'die_temperature', 'imu_temperature',
                               'temperature_c', 'temp_c', 'celsius', 'temperature_degc'})
"""Header names of the sensor temperature's column (any name ending in ``_temperature`` or
``_temp`` too, and ``T (C)``)."""


@dataclass(frozen=True)
class InputColumns:
    """The columns of the robot's own field's inputs in a text log: (field, header name) of the
    interference inputs, and of the temperature with the offset and scale to degrees Celsius."""

    inputs: tuple[tuple[int, str], ...] = ()
    temperature: tuple[int, str] | None = None
    celsius: tuple[float, float] = (0.0, 1.0)
    """(offset, scale): degrees Celsius = (value + offset) * scale (a header in K or F)."""

    @property
    def fields(self) -> tuple[int, ...]:
        """Inputs first, then the temperature (TextLayout.extra)."""
        return (*(index for index, _ in self.inputs),
                *(() if self.temperature is None else (self.temperature[0],)))


def _header_before_data(lines: list[str]) -> tuple[list[str], int] | None:
    """(the header's cells aligned with the data fields, the field count), or None."""
    found = _data_pattern(lines)
    if found is None:
        return None
    field_count, _, position = found
    for line in reversed(lines[:position]):
        if line.strip():
            cells = _header_cells(line, field_count)
            return None if cells is None else (cells, field_count)
    return None


def _column_role(cell: str) -> tuple[str | None, str | None]:
    """('input' | 'temperature' | None, the unit the header gives) of a header cell."""
    name, unit = _time_name(cell)
    if name in CURRENT_NAMES or name.endswith('_current'):
        return 'input', unit
    if (name in TEMPERATURE_NAMES or name.endswith(('_temperature', '_temp'))
            or (name == 't' and unit in CELSIUS_UNITS | KELVIN_UNITS | FAHRENHEIT_UNITS)):
        return 'temperature', unit
    return None, unit


def _named_column(spec: str, cells: list[str] | None, field_count: int | None, taken: set[int],
                  option: str, source: str) -> tuple[int, str]:
    """(field, name) of one column an option names by header name or zero-based index."""
    spec = spec.strip()
    if re.fullmatch(r'\d+', spec):
        index = int(spec)
        if field_count is not None and index >= field_count:
            raise RecordingError(f'{source}: {option} {spec}: the data lines have only '
                                 f'{field_count} fields (zero-based indices)')
        name = cells[index].strip() if cells is not None else f'field {index}'
    else:
        found = field_named(spec, cells or (), option, source)
        if found is None:
            names = ', '.join(cell.strip() for cell in cells or ()) or 'no header line'
            raise RecordingError(f"{source}: {option}: no column named '{spec}' (columns: "
                                 f'{names}); give a header name or a zero-based field index')
        index = found
        name = cells[index].strip()  # type: ignore[index]
    if index in taken:
        raise RecordingError(f'{source}: {option} {spec} names a field already read (the '
                             'magnetometer, the accelerometer, the gyroscope, the time or '
                             'another input)')
    return index, name


def compensation_columns(lines: list[str], taken: Sequence[int], source: str,
                         inputs: str | None = None, temperature: str | None = None
                         ) -> InputColumns:
    """The interference inputs' and the temperature's columns: those the options name (header
    names or zero-based indices, ``inputs`` comma-separated), else those the header names
    (CURRENT_NAMES, TEMPERATURE_NAMES); ``''`` for an option: none."""
    header = _header_before_data(lines)
    cells, field_count = header if header is not None else (None, None)
    used = set(taken)
    chosen_inputs: list[tuple[int, str]] = []
    chosen_temperature = None
    unit = None
    if inputs is not None:
        for spec in (part for part in inputs.split(',') if part.strip()):
            index, name = _named_column(spec, cells, field_count, used, '--input-columns',
                                        source)
            used.add(index)
            chosen_inputs.append((index, name))
    if temperature is not None and temperature.strip():
        chosen_temperature = _named_column(temperature, cells, field_count, used,
                                           '--temperature-column', source)
        used.add(chosen_temperature[0])
        unit = _column_role(chosen_temperature[1])[1]
    for index, cell in enumerate(cells or ()):
        if index in used:
            continue
        role, cell_unit = _column_role(cell)
        if role == 'input' and inputs is None:
            chosen_inputs.append((index, cell.strip()))
        elif role == 'temperature' and temperature is None and chosen_temperature is None:
            chosen_temperature, unit = (index, cell.strip()), cell_unit
    names = [name for _, name in chosen_inputs]
    repeated = [name for name in dict.fromkeys(names) if names.count(name) > 1]
    if repeated:  # K is kept and applied by input name, on the robot too
        fields = ', '.join(str(index) for index, name in chosen_inputs if name == repeated[0])
        raise RecordingError(f"{source}: input columns {fields} are all named '{repeated[0]}': a "
                             'compensation tells its inputs apart by name; rename them in the '
                             'header, or choose one with --input-columns')
    celsius = (0.0, 1.0)
    if unit in KELVIN_UNITS:
        celsius = (-273.15, 1.0)
    elif unit in FAHRENHEIT_UNITS:
        celsius = (-32.0, 5.0 / 9.0)
    return InputColumns(tuple(chosen_inputs), chosen_temperature, celsius)


def input_values(values: np.ndarray, name: str, kind: str) -> tuple[np.ndarray, list[str]]:
    """The column's values with the unusable ones NaN, and what was wrong with them, counted and
    named: garbage or NaN/Inf, temperatures no sensor reads, or a column that never varied
    (nothing to learn from)."""
    values = np.array(values, dtype=float)
    problems = []
    bad = ~np.isfinite(values)
    if kind == 'temperature':
        implausible = ~bad & ((values < -60.0) | (values > 200.0))
        if implausible.any():
            problems.append(f"temperature column '{name}': {int(implausible.sum())} values "
                            'outside -60..200 degC ignored (is it in degrees Celsius?)')
        values[implausible] = math.nan
    if bad.any():
        problems.append(f"{kind} column '{name}': {int(bad.sum())} of {len(values)} rows not a "
                        'finite number (text, empty, NaN or Inf) ignored')
        values[bad] = math.nan
    usable = values[np.isfinite(values)]
    what = 'temperature' if kind == 'temperature' else 'current'
    if len(usable) == 0:
        problems.append(f"{kind} column '{name}': no usable value, so it is not used")
    elif float(np.ptp(usable)) == 0.0:
        problems.append(f"{kind} column '{name}': the {what} never varied (always "
                        f'{usable[0]:g}), so nothing can be learned from it')
    return values, problems


def _compensation_extras(table: np.ndarray, chosen: InputColumns) -> dict[str, object]:
    """Recording's inputs, input_names, temperature and input_problems from the table's extra
    columns (3 onwards); a column with no usable value is left out."""
    extras: dict[str, object] = {}
    problems: list[str] = []
    inputs, names = [], []
    for position, (_, name) in enumerate(chosen.inputs):
        values, found = input_values(table[:, 3 + position], name, 'input')
        problems += found
        if np.isfinite(values).any():
            inputs.append(values)
            names.append(name)
    if inputs:
        extras['inputs'] = np.column_stack(inputs)
        extras['input_names'] = tuple(names)
    if chosen.temperature is not None:
        offset, scale = chosen.celsius
        raw = (table[:, 3 + len(chosen.inputs)] + offset) * scale
        values, found = input_values(raw, chosen.temperature[1], 'temperature')
        problems += found
        if np.isfinite(values).any():
            extras['temperature'] = values
    extras['input_problems'] = tuple(problems)
    return extras
