# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Which fields of a text log's lines hold a sensor's x, y, z: names, labels, units, layouts."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
import re

import numpy as np

from mag_calibrator_ros.calibration.fit.earth_field import TESLA_PER_UNIT
from mag_calibrator_ros.tools.recording_lines import COMMENT_PREFIXES, _is_comment, _number, _split
from mag_calibrator_ros.tools.recording_value import RecordingError


def parse_columns(spec: str, option: str = '--columns'
                  ) -> tuple[int, int, int] | tuple[str, str, str]:
    """Parse ``'1,3,5'`` (zero-based field indices) or ``'mx,my,mz'`` (header names)."""
    parts = [part.strip() for part in re.split(r'[,\s]+', spec.strip()) if part.strip()]
    usage = (f"bad {option} '{spec}': give three zero-based field indices such as 0,1,2 "
             f'(1,3,5 for "Mx 144 My -270 Mz 415") or three header names such as mx,my,mz')
    if len(parts) != 3:
        raise RecordingError(usage)
    if all(re.fullmatch(r'[+-]?\d+', part) for part in parts):
        indices = tuple(int(part) for part in parts)
        if min(indices) < 0 or len(set(indices)) != 3:
            raise RecordingError(usage)
        return indices  # type: ignore[return-value]
    if any(re.fullmatch(r'[+-]?[\d.]+', part) for part in parts):
        raise RecordingError(usage)
    names = tuple(part.lower() for part in parts)
    if len(set(names)) != 3:
        raise RecordingError(usage)
    return names  # type: ignore[return-value]


@dataclass(frozen=True)
class TextLayout:
    """Which fields hold x, y, z; ``field_count`` set when every data line must have that many.
    ``numpy_fields``: the data lines are that many plain numbers split by ``delimiter`` (',',
    ';', '\t', or None for white space), so numpy can convert a block of them at once."""

    indices: tuple[int, int, int]
    field_count: int | None
    description: str
    notes: tuple[str, ...] = ()
    delimiter: str | None = None
    numpy_fields: int | None = None
    units: str | None = None
    """The unit the header gives the chosen columns (``Magnetometer X (uT)``), else None."""
    time_index: int | None = None
    """The field of the time column a header names (:func:`time_column`), else None."""
    extra: tuple[int, ...] = ()
    """Fields read beside x, y, z that may be unusable (the compensation's inputs, temperature):
    NaN in their row then, never a reason to drop the reading (:func:`compensation_columns`)."""

    @property
    def fields(self) -> tuple[int, ...]:
        """The fields read from each line: x, y, z, the extra fields, then the time when there
        is one (always the last)."""
        fields = (*self.indices, *self.extra)
        return fields if self.time_index is None else (*fields, self.time_index)


SENSOR_ROLES = ('magnetometer', 'accelerometer', 'gyroscope')
"""Sensors a header can name; :func:`column_roles` finds each one's x, y, z columns."""

_ROLE_WORDS = {
    'magnetometer': ('mag', {'magnetic', 'compass', 'bfield'}, {'m', 'b', 'h'}),
    'accelerometer': ('acc', {'linear'}, {'a'}),
    'gyroscope': ('gyr', {'omega', 'angular', 'rate'}, {'g', 'w'}),
}
"""Per sensor: the prefix of its words (mag, magn, magnetometer; acc, accel, acceleration; gyr,
gyro), other words naming it (field.magnetic_field.x, linear_acceleration.x,
angular_velocity.x) and its one-letter abbreviations (mx, Bx, Hx; ax; gx, wx), which count only
next to the axis (``accelerometer_m_s2[0]`` is no magnetometer)."""
_OTHER_WORDS = {
    'offset', 'offsets', 'ofs', 'bias', 'mo', 'motor', 'orientation', 'quaternion', 'quat', 'q',
    'euler', 'pos', 'position', 'pose', 'att', 'attitude', 'angle', 'gps', 'cov', 'covariance',
    'std', 'var', 'scale', 'error', 'err',
}
"""Words naming x, y, z columns that are no sensor reading (ArduPilot's OfsX and MOX, a pose)."""
_AXES = {'x': 0, 'y': 1, 'z': 2}
_INDEX_AXIS = re.compile(r'\[([012])\]\s*$')  # PX4: magnetometer_ga[0]
_INDEX = re.compile(r'\[\d+\]')  # an array's element, part of a name: esc[1].current
_UNITS = re.compile(r'\([^)]*\)|\[[^\]]*\]|\{[^}]*\}')  # "Bx (µT)", "mag_x [uT]"
_CAMEL = re.compile(r'(?<=[a-z0-9])(?=[A-Z])')  # magX -> mag_X
_COMPACT = re.compile(r'([a-z]+?)([xyz])')  # mx, gyrox, ofsx


@dataclass(frozen=True)
class ColumnRoles:
    """What a header says about its columns: the x, y, z field indices of each sensor it names.

    ``sensors`` maps a role from SENSOR_ROLES to its candidate (x, y, z) index triplets, in
    header order; ``unlabelled`` holds triplets named by their axis alone (``x, y, z``, or a
    prefix no rule knows); ``labels`` names every triplet for messages, e.g. 'mx,my,mz'.
    """

    sensors: dict[str, tuple[tuple[int, int, int], ...]]
    unlabelled: tuple[tuple[int, int, int], ...]
    labels: dict[tuple[int, int, int], str]

    @property
    def names_triplets(self) -> bool:
        return bool(self.unlabelled) or any(self.sensors.values())

    def describe(self, triplets: Sequence[tuple[int, int, int]]) -> str:
        return '; '.join(f'{self.labels[t]} (fields {",".join(map(str, t))})' for t in triplets)


def _axis_and_group(name: str) -> tuple[int, str, tuple[str, ...]] | None:
    """(axis, role, words) for one column name, or None when it names no axis.

    Units in brackets are dropped, camelCase is split, and the axis is the last x, y or z word
    (``mag_x_raw``: the words after it qualify the group), a trailing [0]/[1]/[2] (PX4), or the
    last letter of a short form (``mx``, ``gyrox``, ``mx_raw``).
    """
    index = _INDEX_AXIS.search(name)
    axis = None if index is None else int(index.group(1))
    text = _CAMEL.sub('_', _UNITS.sub(' ', name if index is None else name[:index.start()]))
    before = re.findall(r'[a-z0-9]+', text.lower())
    after: list[str] = []
    if axis is None:
        found = [i for i, word in enumerate(before) if word in _AXES]
        if found:
            position = found[-1]
            axis = _AXES[before[position]]
            before, after = before[:position], before[position + 1:]
        else:
            for position in reversed(range(len(before))):
                compact = _COMPACT.fullmatch(before[position])
                if compact and _known(compact.group(1)):
                    axis = _AXES[compact.group(2)]
                    before, after = [*before[:position], compact.group(1)], before[position + 1:]
                    break
    if axis is None:
        return None
    return axis, _role(before, after), (*before, '|', *after)


def _known(word: str) -> bool:
    """A word a short form may end in an axis after (``mx``, ``gyrox``, ``ofsx``; not
    ``index``)."""
    return word in _OTHER_WORDS or _role([word]) != 'unlabelled'


def _role(before: Sequence[str], after: Sequence[str] = ()) -> str:
    """'other' when a word names no reading; else the sensor a word names (a one-letter
    abbreviation only right before the axis); else 'unlabelled'."""
    words = [*before, *after]
    if any(word in _OTHER_WORDS for word in words):
        return 'other'
    for word in words:
        for role, (prefix, names, _) in _ROLE_WORDS.items():
            if word.startswith(prefix) or word in names:
                return role
    if before:
        for role, (_, _, letters) in _ROLE_WORDS.items():
            if before[-1] in letters:
                return role
    return 'unlabelled'


def column_roles(names: Sequence[str]) -> ColumnRoles:
    """Group column names into the x, y, z triplets of each sensor they name.

    Recognises the usual styles: ``mx``, ``mag_x``, ``magX``, ``MagX``, ``magnetometer_x``,
    ``Bx``, ``Magnetic field x (µT)``, ``field.magnetic_field.x``, ``magnetometer_ga[0]``;
    ``ax``/``acc_x``/``accelX``/``linear_acceleration.x`` for the accelerometer and
    ``gx``/``gyro_x``/``angular_velocity.x`` for the gyroscope. Columns of one triplet share
    everything but the axis (``mx_raw, my_raw, mz_raw`` and ``mx_cal ...`` are two triplets).
    """
    groups: dict[tuple[str, tuple[str, ...]], dict[int, list[int]]] = {}
    for field_index, name in enumerate(names):
        parsed = _axis_and_group(name)
        if parsed is not None:
            axis, role, words = parsed
            groups.setdefault((role, words), {}).setdefault(axis, []).append(field_index)
    sensors: dict[str, list[tuple[int, int, int]]] = {role: [] for role in SENSOR_ROLES}
    unlabelled: list[tuple[int, int, int]] = []
    labels: dict[tuple[int, int, int], str] = {}
    for (role, _), axes in groups.items():
        if sorted(axes) != [0, 1, 2] or any(len(fields) != 1 for fields in axes.values()):
            continue
        triplet = (axes[0][0], axes[1][0], axes[2][0])
        labels[triplet] = ','.join(names[i].strip() for i in triplet)
        if role in sensors:
            sensors[role].append(triplet)
        elif role == 'unlabelled':
            unlabelled.append(triplet)
    order = sorted  # header order: by the x column
    return ColumnRoles({role: tuple(order(found)) for role, found in sensors.items()},
                       tuple(order(unlabelled)), labels)


def sensor_columns(
    roles: ColumnRoles, role: str = 'magnetometer'
) -> tuple[int, int, int] | str:
    """The (x, y, z) fields of ``role``, or why the header does not say which (naming every
    candidate, for a message asking for --columns)."""
    own = roles.sensors[role]
    if len(own) == 1:
        return own[0]
    if len(own) > 1:
        return f'the header names {len(own)} {role} column sets: {roles.describe(own)}'
    others = [(name, found) for name, found in roles.sensors.items() if name != role and found]
    named = '; '.join(f'{name} {roles.describe(found)}' for name, found in others)
    if len(roles.unlabelled) == 1 and not others and role == 'magnetometer':
        return roles.unlabelled[0]  # a magnetometer log whose header says only x, y, z
    if roles.unlabelled:
        unnamed = roles.describe(roles.unlabelled)
        beside = f' beside {named}' if named else ''
        return f'the header names no {role} columns, only unlabelled {unnamed}{beside}'
    if named:
        return f'the header names no {role} columns, only {named}'
    return 'the header names no x, y, z columns'


def _header_cells(line: str, field_count: int) -> list[str] | None:
    """A header line's names aligned with the data fields: split as data lines are, or on one
    delimiter when names hold spaces ("Magnetic field x (µT)"); None when they do not align."""
    text = line.strip()
    for prefix in COMMENT_PREFIXES:  # '%time,field.magnetic_field.x' (rostopic echo -p)
        if text.startswith(prefix):
            text = text[len(prefix):].strip()
    candidates = [_split(text)]
    candidates += [[cell.strip().strip('"\'') for cell in text.split(delimiter)]
                   for delimiter in (',', '\t', ';') if delimiter in text]
    for cells in candidates:
        if len(cells) == field_count:
            return cells
    return None


def _inline_labels(tokens: list[str]) -> list[str]:
    """'Mx 144 My -270 Mz 415': each number named by the word before it ('' when none)."""
    return ['' if _number(token) is None or i == 0 or _number(tokens[i - 1]) is not None
            else tokens[i - 1].rstrip(':') for i, token in enumerate(tokens)]


def detect_layout(lines: list[str], source: str, role: str = 'magnetometer',
                  guess: bool = True, read_beside: tuple[int, ...] = ()) -> TextLayout:
    """Which fields hold ``role``'s x, y, z: named by a header or labels when there are any,
    else the only three numeric fields of the most common data line, or (``guess``) the only
    three that are neither constant nor time stamps (:func:`_axis_candidates`). Raises
    RecordingError, naming the candidates, when nothing decides (more numeric fields than three
    and no names, several candidate sets, or names for other sensors only). The note names the
    other sensors' columns as ignored, but for ``read_beside`` (the accelerometer's and the
    gyroscope's, when the reader takes them too)."""
    found = _data_pattern(lines)
    if found is None:
        raise RecordingError(f'{source}: no line with three numeric fields in the first '
                             f'{len(lines)} lines (not a magnetometer recording?)')
    field_count, numeric, position = found
    data_line = lines[position]
    delimiter, numpy_fields = _numpy_reading(data_line, field_count, numeric)
    roles = _named_roles(lines[:position], data_line, field_count)
    if roles is not None:
        chosen = sensor_columns(roles, role)
        if isinstance(chosen, str):
            raise RecordingError(f'{source}: {chosen}: choose the {role} columns with --columns '
                                 '(three header names or zero-based field indices)')
        others = [f'{name} {roles.describe(unread)}' for name, found in roles.sensors.items()
                  if name != role and (unread := [triplet for triplet in found
                                                  if not set(triplet) <= set(read_beside)])]
        units = header_units(roles.labels[chosen])
        notes = (f'{role} columns {roles.labels[chosen]} (fields '
                 f'{",".join(map(str, chosen))}) chosen by their names'
                 + (f'; ignored {"; ".join(others)}' if others else '')
                 + (f'; units {units} from the header' if units else ''),)
        return TextLayout(chosen, field_count,
                       f'columns {roles.labels[chosen]} (fields {",".join(map(str, chosen))})',
                       notes, delimiter, numpy_fields, units)
    if role == 'magnetometer' and _magnetic_field_echo(data_line):
        return TextLayout((3, 4, 5), field_count,
                          'ros2 topic echo --csv of sensor_msgs/MagneticField (fields 3,4,5)',
                          ('fields 3,4,5: magnetic_field x, y, z of ros2 topic echo --csv (sec, '
                           'nanosec, frame_id, the field, its covariance): tesla, REP-103',),
                          delimiter, numpy_fields, 'T')
    if len(numeric) > 3:
        candidates, ignored = (_axis_candidates(lines, field_count, numeric) if guess
                               else (numeric, ''))
        if len(candidates) == 3:
            fields = ','.join(map(str, candidates))
            return TextLayout(candidates, field_count, f'fields {fields}',  # type: ignore[arg-type]
                              (f'fields {fields}: the numeric fields besides {ignored} '
                               '(choose others with --columns)',),
                              delimiter, numpy_fields)
        guesses = candidates if len(candidates) > 3 else numeric
        example = ','.join(map(str, guesses[-3:]))
        raise RecordingError(
            f'{source}: lines have {len(numeric)} numeric fields '
            f'({",".join(map(str, numeric))}) and no header names the {role} columns: choose '
            f'its three with --columns (zero-based field indices, e.g. --columns {example}); '
            f'first data line: {" ".join(data_line.split())[:80]}')
    indices = (numeric[0], numeric[1], numeric[2])
    return TextLayout(indices, field_count, f'fields {",".join(map(str, indices))}', (), delimiter,
                   numpy_fields)


_UNIT_WORDS = {
    **{unit.lower(): unit for unit in TESLA_PER_UNIT},
    'ut': 'uT', '\u00b5t': 'uT', '\u03bct': 'uT', 'mt': 'mT', 'ga': 'G', 'gauss': 'G',
    'mgauss': 'mG', 'mga': 'mG',
}
"""A header's unit words (any case) -> the unit's name in TESLA_PER_UNIT."""


_UNIT_SUFFIX = re.compile(r'_(ga|gauss|ut|nt|mgauss)(?:\[[012]\])?\s*$', re.IGNORECASE)
"""A field unit as the name's last word: PX4's ``magnetometer_ga[0]`` (gauss, its uORB
convention, as ``accelerometer_m_s2``), ``mag_x_uT``."""


def header_units(labels: str) -> str | None:
    """The unit that every one of the three comma-joined column names gives in brackets
    (``Magnetometer X (uT)``, ``mag_x [nT]``) or as its last word (``magnetometer_ga[0]``),
    when it is a unit of magnetic field; else None."""
    found = set()
    for name in labels.split(','):
        bracketed = [unit for unit in _UNITS.findall(name) if not _INDEX.fullmatch(unit)]
        suffix = _UNIT_SUFFIX.search(name)
        if len(bracketed) + (suffix is not None) != 1:
            return None
        word = bracketed[0][1:-1] if bracketed else suffix.group(1)  # type: ignore[union-attr]
        found.add(_UNIT_WORDS.get(word.strip().lower()))
    if len(found) != 1:
        return None
    return found.pop()


def _axis_candidates(
    lines: list[str], field_count: int, numeric: tuple[int, ...]
) -> tuple[tuple[int, ...], str]:
    """The numeric fields that may be a magnetometer axis, and words for those that may not:
    fields constant over the lines (a message's covariance, a flag) and clocks (integers that
    never decrease: time stamps, sequence numbers; nanoseconds beside a seconds stamp)."""
    rows = []
    for line in lines:
        if not line.strip() or _is_comment(line):
            continue
        tokens = _split(line)
        if len(tokens) == field_count:
            values = [_number(tokens[i]) for i in numeric]
            if all(value is not None for value in values):
                rows.append(values)
    if len(rows) < 3:
        return numeric, ''
    table = np.array(rows, dtype=np.float64)
    with np.errstate(invalid='ignore'):
        constant = np.all(table == table[0], axis=0)
        whole = np.all(np.isfinite(table) & (table == np.round(table)), axis=0)
        clock = whole & ~constant & np.all(np.diff(table, axis=0) >= 0, axis=0)
        after_stamp = np.zeros(len(numeric), dtype=bool)
        after_stamp[1:] = whole[:-1] & (clock[:-1] | constant[:-1] & (table[0, :-1] >= 1e8))
        nanoseconds = (whole & ~constant & after_stamp
                       & np.all((table >= 0) & (table < 1e9), axis=0))
    dropped = constant | clock | nanoseconds
    candidates = tuple(index for index, drop in zip(numeric, dropped, strict=True) if not drop)
    words = []
    for mask, what in ((constant, 'constant'), (clock | nanoseconds, 'time stamps')):
        if mask.any():
            fields = ','.join(str(i) for i, m in zip(numeric, mask, strict=True) if m)
            words.append(f'{what} {fields}')
    return candidates, ' and '.join(words)


def _data_pattern(lines: list[str]) -> tuple[int, tuple[int, ...], int] | None:
    """The most common data line among ``lines``: (field count, numeric fields, position of its
    first line); None when no line has three numeric fields."""
    patterns: Counter[tuple[int, tuple[int, ...]]] = Counter()
    first: dict[tuple[int, tuple[int, ...]], int] = {}
    for position, line in enumerate(lines):
        if not line.strip() or _is_comment(line):
            continue
        tokens = _split(line)
        numeric = tuple(i for i, token in enumerate(tokens) if _number(token) is not None)
        if len(numeric) >= 3:
            patterns[(len(tokens), numeric)] += 1
            first.setdefault((len(tokens), numeric), position)
    if not patterns:
        return None
    (field_count, numeric), _ = patterns.most_common(1)[0]
    return field_count, numeric, first[(field_count, numeric)]


def _named_roles(before: list[str], data_line: str, field_count: int) -> ColumnRoles | None:
    """The roles a header (the last line before the data whose names align with the fields) or
    the data line's own labels name; None when nothing names a triplet."""
    for line in reversed(before):
        if not line.strip():
            continue
        cells = _header_cells(line, field_count)
        if cells is not None:
            roles = column_roles(cells)
            if roles.names_triplets:
                return roles
        break
    roles = column_roles(_inline_labels(_split(data_line)))
    return roles if roles.names_triplets else None


def _magnetic_field_echo(line: str) -> bool:
    """Whether ``line`` is a sensor_msgs/MagneticField as ``ros2 topic echo --csv`` prints it:
    sec, nanosec, frame_id (not a number), then the field's three and the covariance's nine."""
    parts = line.strip().split(',')
    if len(parts) != 15 or not (parts[0].isdigit() and parts[1].isdigit()):
        return False
    if int(parts[1]) >= 1_000_000_000 or _number(parts[2]) is not None:
        return False
    return all(_number(part) is not None for part in parts[3:])


def _numpy_reading(
    line: str, field_count: int, numeric: tuple[int, ...]
) -> tuple[str | None, int | None]:
    """(delimiter, field count) for numpy to read blocks of lines like this one, which it can
    when every field is a number; else (None, None)."""
    if len(numeric) != field_count:
        return None, None
    for delimiter in (',', ';', '\t'):
        if delimiter in line:
            return delimiter, field_count
    return None, field_count


def _explicit_layout(spec: str, lines: list[str], source: str, option: str = '--columns'
                     ) -> TextLayout:
    columns = parse_columns(spec, option)
    found = _data_pattern(lines)
    delimiter, numpy_fields = None, None
    if found is not None:
        delimiter, numpy_fields = _numpy_reading(lines[found[2]], found[0], found[1])
    if isinstance(columns[0], int):
        indices = tuple(int(c) for c in columns)
        return TextLayout(indices, None, f'fields {",".join(map(str, indices))}', (),  # type: ignore[arg-type]
                       delimiter, numpy_fields)
    for line in lines if found is not None else ():
        cells = _header_cells(line, found[0])  # names that align with the data fields only:
        if cells is not None:  # the words of 'Time (s),mx (uT)' are not its fields
            named = [field_named(str(name), cells, f"{option} '{spec}'", source)
                     for name in columns]
            if None not in named:
                indices = tuple(named)
                return TextLayout(indices, None, f'columns {",".join(map(str, columns))} '  # type: ignore[arg-type]
                               f'(fields {",".join(map(str, indices))})', (), delimiter,
                               numpy_fields, header_units(','.join(cells[i] for i in indices)))
    raise RecordingError(f"{source}: no header line names all of {option} '{spec}' "
                         f'in the first {len(lines)} lines')


def field_named(name: str, cells: Sequence[str], option: str, source: str) -> int | None:
    """The field a header ``cells`` (aligned with the data fields) names ``name``, any case: the
    cell that is the name, else, for a name without a unit of its own, the one whose name is it
    without its unit (``current`` names ``current (A)``, as a header's unit never is part of a
    name; an index such as PX4's ``[0]`` is); None when no cell does. Raises RecordingError
    when several do."""
    def plain(text: str) -> str:
        unitless = _UNITS.sub(lambda bracket: bracket[0] if _INDEX.fullmatch(bracket[0])
                              else ' ', text)
        return ' '.join(unitless.split()).lower()

    lowered = [cell.strip().strip('"\'').lower() for cell in cells]
    exact = [i for i, cell in enumerate(lowered) if cell == name.strip().lower()]
    named = [i for i, cell in enumerate(lowered) if plain(cell) == plain(name)]
    for matches in (exact, named if plain(name) == ' '.join(name.split()).lower() else []):
        if len(matches) == 1:
            return matches[0]
        if matches:
            raise RecordingError(f"{source}: {option}: '{name.strip()}' names several columns ("
                                 + ', '.join(f'{cells[i].strip()} (field {i})' for i in matches)
                                 + '): give a zero-based field index')
    return None
