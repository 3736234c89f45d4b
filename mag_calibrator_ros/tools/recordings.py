"""Read magnetometer recordings into an ``(n, 3)`` float64 array for the offline fit.

Text (a file or ``-`` for stdin): CSV, TSV, whitespace or ``;`` separated, with or without a
header, LF or CRLF, and labelled lines such as ``Mx 144 My -270 Mz 415``. Each line is split into
*fields* on whitespace, ``,``, ``;`` and ``=``. Without ``columns`` the layout is detected from the
first lines: the most common pattern of numeric fields is the data; a header (or the labels in
the lines) naming the magnetometer's x, y, z picks those fields (``mx``, ``mag_x``, ``magX``,
``Bx``, ``Magnetic field x (µT)``, ``field.magnetic_field.x`` ..., see :func:`column_roles`), and
without names the three numeric fields are x, y, z (``Mx 144 My -270 Mz 415`` -> fields 1, 3, 5).
A file that does not say which fields are the magnetometer's (more numeric fields than three and no
names, several magnetometer sets, only accelerometer or gyroscope names) raises ``RecordingError``
naming the candidates: choose with ``columns``, three **zero-based** field indices (``'1,3,5'``
picks 144, -270, 415 from that line) or three header names (``'mx,my,mz'``; a name matches a header
cell with or without its unit, ``mx (uT)``, as the compensation's column options do). Without
names, numeric fields that stay constant (a message's covariance) or count time (stamps, sequence
numbers) are not candidates, so ``ros2 topic echo --csv /imu/mag`` gives the field (fields 3, 4,
5). A header's units (``Magnetometer X (uT)``) are the recording's units. ``;``-separated numbers
with decimal commas (``12,5;-3,2;40,1``) are read as such.
``ros2 topic echo /imu/mag`` (YAML documents separated by ``---``) is read message by message,
in tesla. Lines are converted a block at a time (numpy for plain numbers) into one growing
float array, so memory holds the samples (8 bytes a value), not the text; a line longer than
``MAX_LINE_CHARS`` (binary data, a NUL tail) is refused.

Bags: rosbag2 (a bag directory, or a single ``.db3`` / ``.mcap`` file) and ROS 1 (a ``.bag``
file, as most IMU drivers, filters and public robot datasets ship their data): the
``sensor_msgs/MagneticField`` topic named by ``topic``, or the only such topic in the bag, each
message with its header stamp; optionally an Imu topic paired with it by stamp. Values are
tesla (REP-103).

Time: a text log whose header names a time column (``Time (s)``, ``time``, ``t``, ``stamp``,
``timestamp``, ``millis`` ...) is stamped by it, in the unit its header gives or, without one,
the unit its values show (seconds or milliseconds, :func:`time_unit`); ``Recording.time_source``
says which column and unit were taken. A log without one has ``stamps`` None: its rate is
unknown, and nothing that reads it may depend on a guessed one.

The robot's own field (``compensation``): a text log's current and temperature columns, by
header name (:func:`compensation_columns`) or named; a bag's ``sensor_msgs/BatteryState``
(``current``) and ``sensor_msgs/Temperature`` topics, paired with each reading by stamp. A bad
value there (text, NaN, a temperature no sensor reads) is NaN in ``Recording.inputs`` /
``temperature``, counted and named in ``input_problems`` (a column that never varied too), and
never drops the reading.

Nothing is dropped silently: every skipped line or message is counted by reason in
``Recording.skipped`` (NaN/Inf, values beyond ``screening.MAX_READING``, ...). Problems a user
must fix raise ``RecordingError`` with a one-line message naming the source and what is wrong.
"""

from __future__ import annotations

from array import array
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
import itertools
import math
from pathlib import Path
import re
import sys
from typing import TextIO
import warnings

import numpy as np

from mag_calibrator_ros.calibration.fit.earth_field import TESLA_PER_UNIT
from mag_calibrator_ros.calibration.live.pairing import PAIR_TOLERANCE_NS
from mag_calibrator_ros.calibration.live.screening import MAX_FORWARD_JUMP_NS, MAX_READING

MAGNETIC_FIELD = 'sensor_msgs/msg/MagneticField'
IMU = 'sensor_msgs/msg/Imu'
BATTERY_STATE = 'sensor_msgs/msg/BatteryState'
TEMPERATURE_MSG = 'sensor_msgs/msg/Temperature'
BAG_SUFFIXES = ('.db3', '.mcap')
ROS1_SUFFIX = '.bag'
ROS1_MAGIC = b'#ROSBAG V2.0'
BINARY_CONTROL_FRACTION = 0.1
"""Share of control bytes in the first 4 KiB that marks a binary file (serial noise has fewer)."""
STDIN = '-'

FIELD_SEPARATORS = re.compile(r'[\s,;=]+')
COMMENT_PREFIXES = ('#', '%', '//')
LAYOUT_SAMPLE_LINES = 1000
"""Lines inspected to detect the layout (and find a header) before streaming the rest."""
BLOCK_LINES = 8192
"""Text lines read and converted at a time: a block of plain numbers is one numpy call, and
memory holds the samples, never the text or a Python object per value."""
MAX_LINE_CHARS = 1 << 16
"""Longest line a text recording may have. Real lines are a few hundred characters (a
``ros2 topic echo --csv`` of an Imu message about a thousand); a longer one is binary data or a
NUL-filled tail without line breaks, refused before it fills memory."""
BLOCK_CHARS = 1 << 22
"""Most characters held at a time: the layout sample and each block stop here even when their
lines are long, so the text in memory stays bounded whatever the file."""

SKIP_REASONS = {
    'header': 'header',
    'comment': 'comment',
    'wrong_field_count': 'field count differs from the data lines',
    'too_few_fields': 'too few fields for the chosen columns',
    'not_numeric': 'not numeric',
    'non_finite': 'NaN/Inf',
    'out_of_range': f'beyond ±{MAX_READING:.0e} (no magnetometer reads that in any unit)',
    'undecodable': 'undecodable message',
    'incomplete': 'message without magnetic_field x, y, z',
    'bad_time': 'time column not a finite number',
}
"""Why a line or message was skipped: key -> words for the summary."""

ProgressCallback = Callable[[int, int | None], None]
"""``progress(done, total)``: bytes for text, messages for bags; ``total`` None when unknown."""


class RecordingError(ValueError):
    """The recording cannot be used; the message is one line a user can act on."""


@dataclass(frozen=True)
class Recording:
    """Samples read from one source, and an honest account of what was skipped."""

    samples: np.ndarray
    source: str
    kind: str
    """'text', 'rosbag2' or 'ROS 1 bag'."""
    layout: str
    """Which fields or topic the samples came from, e.g. 'fields 1,3,5' or 'topic /imu/mag'."""
    skipped: dict[str, int] = field(default_factory=dict)
    units: str | None = None
    """Units implied by the format ('T' for bags); None when the file does not say."""
    notes: tuple[str, ...] = ()
    """Things the user should know, e.g. that more numeric fields were present than used."""
    accel: np.ndarray | None = None
    """(n, 3) accelerometer rows beside ``samples`` (``read_paired_recording``, or a bag's Imu
    topic paired by stamp, NaN where no sample was near), else None."""
    gyro: np.ndarray | None = None
    """(n, 3) angular rates (rad/s) beside ``samples`` from a bag's Imu topic, else None."""
    stamps: np.ndarray | None = None
    """(n,) seconds of each row (a bag's header stamps, a log's time column); None when the
    recording has no time."""
    time_source: str | None = None
    """Where ``stamps`` come from, for the user: 'column time (field 0), milliseconds ...'."""
    inputs: np.ndarray | None = None
    """(n, k) interference inputs beside ``samples`` (a text log's current columns, a bag's
    BatteryState ``current`` paired by stamp), NaN where a row has none usable; else None."""
    input_names: tuple[str, ...] = ()
    """The k inputs' names, as the calibration file names them."""
    temperature: np.ndarray | None = None
    """(n,) sensor temperature (degrees Celsius) beside ``samples``, NaN where none; else None."""
    input_problems: tuple[str, ...] = ()
    """What was wrong with those columns or topics, counted and named in the user's terms."""

    @property
    def rows(self) -> int:
        return int(self.samples.shape[0])

    @property
    def rows_skipped(self) -> int:
        return sum(self.skipped.values())

    def describe(self) -> str:
        """One line: source, rows used, where from, and skipped rows by reason."""
        text = f'{self.source}: {self.rows} rows from {self.layout}'
        if self.skipped:
            text += f'; skipped {self.rows_skipped} ({describe_skips(self.skipped)})'
        return text


def describe_skips(skipped: dict[str, int]) -> str:
    """'2 header, 1 NaN/Inf' for a skip counter."""
    return ', '.join(f'{count} {SKIP_REASONS.get(reason, reason)}'
                     for reason, count in skipped.items() if count)


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


def read_recording(
    source: str | Path,
    *,
    columns: str | None = None,
    topic: str | None = None,
    accel_topic: str | None = None,
    min_rows: int = 1,
    stdin: TextIO | None = None,
    progress: ProgressCallback | None = None,
    compensation: tuple[str | None, str | None] | None = None,
) -> Recording:
    """Read any supported recording; ``'-'`` reads text from ``stdin`` (default ``sys.stdin``).
    ``accel_topic``: a bag's Imu topic to pair by stamp (``''``: the only one).
    ``compensation``: read the robot's own field's inputs too: for text (the input columns, the
    temperature column), for a bag (the BatteryState topic, the Temperature topic); None in
    either place finds them by name or type (``compensation_columns``, ``read_rosbag``).

    Raises ``RecordingError`` for missing or unreadable input, options that do not fit the input,
    no usable rows, or fewer than ``min_rows``.
    """
    if str(source) == STDIN:
        if topic is not None or accel_topic is not None:
            raise RecordingError('--topic and --accel apply to a bag, not to text on stdin')
        recording = read_text(stdin if stdin is not None else sys.stdin, 'stdin',
                              columns=columns, progress=progress, compensation=compensation)
    else:
        path = Path(source)
        if is_rosbag(path):
            if columns is not None:
                raise RecordingError(f'{path}: --columns applies to text input, not to a bag '
                                     '(use --topic)')
            recording = read_rosbag(path, topic=topic, accel_topic=accel_topic,
                                    progress=progress, compensation=compensation)
        else:
            if topic is not None or accel_topic is not None:
                option = '--topic' if topic is not None else '--accel'
                hint = ' (a text log: --accel-columns)' if topic is None else ''
                raise RecordingError(f'{path}: {option} applies to rosbag2 or ROS 1 bags (a bag '
                                     f'directory, .db3, .mcap or .bag), not to a text file{hint}')
            recording = read_text_file(path, columns=columns, progress=progress,
                                       compensation=compensation)
    if recording.rows < max(min_rows, 1):
        found = 'no usable rows' if recording.rows == 0 else f'only {recording.rows} usable rows'
        skipped = f'; skipped {describe_skips(recording.skipped)}' if recording.skipped else ''
        need = f' (need at least {min_rows})' if min_rows > 1 else ''
        raise RecordingError(f'{recording.source}: {found} from {recording.layout}{need}{skipped}')
    return recording


def is_rosbag(path: Path) -> bool:
    """A bag directory (has metadata.yaml), a storage file named .db3 / .mcap, or a ROS 1 bag."""
    if path.is_dir():
        return True  # read_rosbag explains when it is not a bag
    return path.suffix.lower() in BAG_SUFFIXES or is_ros1_bag(path)


# --- text ------------------------------------------------------------------------------------


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


def _bounded_lines(stream: Iterable[str], source: str) -> Iterator[str]:
    """The stream's lines, each read with a bound: a line longer than MAX_LINE_CHARS raises
    RecordingError instead of being read whole (a NUL tail is one line of gigabytes)."""
    readline = getattr(stream, 'readline', None)
    lines = iter(stream) if readline is None else iter(lambda: readline(MAX_LINE_CHARS + 1), '')
    for number, line in enumerate(lines, start=1):
        if len(line) > MAX_LINE_CHARS and not (len(line) == MAX_LINE_CHARS + 1
                                               and line.endswith('\n')):
            binary = ' (it holds NUL bytes: binary data)' if '\0' in line else ''
            raise RecordingError(f'{source}: line {number} is longer than {MAX_LINE_CHARS} '
                                 f'characters{binary}: not a text recording')
        yield line


def _head(lines: Iterator[str]) -> list[str]:
    """The first LAYOUT_SAMPLE_LINES lines (fewer when they pass BLOCK_CHARS), to find the
    layout in; the caller streams the rest from ``lines``."""
    return next(_blocks(lines, LAYOUT_SAMPLE_LINES), [])


def _blocks(lines: Iterator[str], max_lines: int = BLOCK_LINES) -> Iterator[list[str]]:
    """Lines in blocks of at most ``max_lines`` lines and about BLOCK_CHARS characters; a
    block is yielded as soon as it is full, so an abandoned generator has read no further."""
    block: list[str] = []
    held = 0
    for line in lines:
        block.append(line)
        held += len(line)
        if len(block) >= max_lines or held >= BLOCK_CHARS:
            yield block
            block, held = [], 0
    if block:
        yield block


class _GrowingRows:
    """Rows of ``width`` floats appended block by block into one ``array('d')`` (which grows in
    place): the samples cost 8 bytes a value while reading, and the result is a view, no copy."""

    def __init__(self, width: int) -> None:
        self.width = width
        self.values = array('d')

    def extend(self, rows: np.ndarray | Sequence[Sequence[float]]) -> None:
        block = np.asarray(rows, dtype=np.float64).reshape(-1, self.width)
        self.values.frombytes(np.ascontiguousarray(block).tobytes())

    def __len__(self) -> int:
        return len(self.values) // self.width

    def result(self) -> np.ndarray:
        return np.frombuffer(self.values, dtype=np.float64).reshape(-1, self.width)


def _refuse_binary(path: Path, head: bytes) -> None:
    if head.startswith(b'SQLite format 3\x00') or head.startswith(b'\x89MCAP'):
        raise RecordingError(f'{path}: looks like a rosbag2 storage file; name it .db3 or .mcap '
                             'or pass its bag directory')
    control = sum(byte < 9 or 13 < byte < 32 for byte in head)
    if control > BINARY_CONTROL_FRACTION * len(head):
        raise RecordingError(f'{path}: binary file, not a text recording or rosbag2 bag')


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


def _split(line: str) -> list[str]:
    return [token.strip('"\'') for token in FIELD_SEPARATORS.split(line.strip()) if token]


def _number(token: str) -> float | None:
    try:
        return float(token)
    except ValueError:
        return None


def _is_text(tokens: list[str]) -> bool:
    """Fewer than three numbers: a title or column names, not a damaged data line."""
    return sum(_number(token) is not None for token in tokens) < 3


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith(COMMENT_PREFIXES)


# --- which columns are the magnetometer's ------------------------------------------------------

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


# --- the robot's own field's inputs in a text log (current, temperature) --------------------

CURRENT_NAMES = frozenset({'current', 'battery_current', 'motor_current', 'bus_current',
                           'current_a', 'amps', 'amperes', 'ibat', 'i_bat'})
"""Header names of an interference input's column (units in brackets dropped; any name ending
in ``_current`` too): the current the robot's motors and battery draw."""
TEMPERATURE_NAMES = frozenset({'temperature', 'temp', 'die_temperature', 'imu_temperature',
                               'temperature_c', 'temp_c', 'celsius', 'temperature_degc'})
"""Header names of the sensor temperature's column (any name ending in ``_temperature`` or
``_temp`` too, and ``T (C)``)."""
CELSIUS_UNITS = frozenset({'c', '\u00b0c', 'degc', 'deg c', 'celsius'})
KELVIN_UNITS = frozenset({'k', 'kelvin'})
FAHRENHEIT_UNITS = frozenset({'f', '\u00b0f', 'degf', 'deg f', 'fahrenheit'})


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
    steps = np.diff(finite)
    steps = steps[steps > 0]
    step = float(np.median(steps)) if len(steps) else 0.0
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


def _stamps(table: np.ndarray, time: TimeColumn | None) -> tuple[np.ndarray | None, str | None]:
    """Seconds of each row from the time column read as the table's last column."""
    if time is None:
        return None, None
    scale, why = time_unit(table[:LAYOUT_SAMPLE_LINES, -1], time.header_unit)
    return table[:, -1] * scale, f"column '{time.name}' (field {time.index}), {why}"


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


_DECIMAL_COMMA = re.compile(r'[+-]?\d*,\d+(?:[eE][+-]?\d+)?')


def _decimal_comma(lines: list[str]) -> bool:
    """Whether the data lines are ``;``-separated numbers with a decimal comma (``12,5;-3,2``:
    a spreadsheet's CSV where the comma is the decimal mark): most lines with a ``;`` and a
    comma have commas only inside such numbers."""
    with_commas = decimal = 0
    for line in lines:
        if ';' not in line or ',' not in line or _is_comment(line):
            continue
        with_commas += 1
        cells = [cell.strip().strip('"\'') for cell in line.split(';')]
        decimal += all(_DECIMAL_COMMA.fullmatch(cell) for cell in cells if ',' in cell)
    return with_commas > 0 and 2 * decimal > with_commas


def _decimal_point(line: str) -> str:
    return line.replace(',', '.')


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


# --- bags: rosbag2 and ROS 1 --------------------------------------------------------------


def read_rosbag(
    path: Path, *, topic: str | None = None, accel_topic: str | None = None,
    progress: ProgressCallback | None = None,
    compensation: tuple[str | None, str | None] | None = None,
) -> Recording:
    """Read ``magnetic_field`` of every message on a MagneticField topic of a rosbag2 bag or a
    ROS 1 ``.bag``, with each message's header stamp (its receive time when the header has
    none). ``accel_topic`` (``''``: the only sensor_msgs Imu topic) adds the Imu sample nearest
    each reading's stamp, within PAIR_TOLERANCE_NS as the node pairs them (NaN when none is):
    its ``linear_acceleration`` as ``accel``, its ``angular_velocity`` as ``gyro``.
    ``compensation`` (BatteryState topic, Temperature topic; None: the only one of its type,
    ``''``: none) adds the battery ``current`` and the ``temperature`` nearest each reading's
    stamp, within the live calibrator's tolerances (``live/compensation.py``)."""
    ros1 = is_ros1_bag(path)
    kind = 'ROS 1 bag' if ros1 else 'rosbag2 bag'
    try:  # only bags need it (and apt ROS users may not have it: README, rosdep#979)
        from rosbags.typesys import Stores, get_typestore
        if ros1:
            from rosbags.rosbag1 import Reader, ReaderError
        else:
            from rosbags.rosbag2 import Reader, ReaderError  # type: ignore[assignment]
    except ImportError as error:
        raise RecordingError(
            f'{path}: reading a {kind} needs the rosbags library ({error}): '
            'pip install rosbags (in a venv, or --user --break-system-packages on Ubuntu 24.04)'
        ) from None

    if not path.exists():
        raise RecordingError(f'{path}: no such file or bag directory')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        raise RecordingError(f'{path}: a directory but not a rosbag2 bag (no metadata.yaml)')
    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    deserialize = typestore.deserialize_ros1 if ros1 else typestore.deserialize_cdr
    skipped: Counter[str] = Counter()
    imu_rows = _GrowingRows(7)
    try:
        with Reader(path) as reader:
            topics = _bag_topics(reader)
            chosen = _choose_topic(path, topics, topic)
            imu_topic = None if accel_topic is None else _choose_topic(
                path, topics, accel_topic or None, IMU, '--accel')
            sides, side_notes = ({}, ()) if compensation is None else _input_topics(
                path, topics, *compensation)
            side_rows: dict[str, list[tuple[float, float]]] = {name: [] for name in sides}
            wanted = {chosen} | ({imu_topic} if imu_topic else set()) | set(sides)
            connections = [c for c in reader.connections if c.topic in wanted]
            total = sum(c.msgcount for c in connections if c.topic == chosen) or None
            mag_rows = _GrowingRows(4)
            pending: list[tuple[float, ...]] = []
            count = 0
            for connection, log_time, rawdata in reader.messages(connections=connections):
                try:
                    message = deserialize(rawdata, connection.msgtype)
                except Exception:  # noqa: BLE001 - a corrupt message is counted, not fatal
                    if connection.topic == chosen:
                        skipped['undecodable'] += 1
                    continue
                if connection.topic in sides:
                    side_rows[connection.topic].append(_side_value(message, log_time))
                    continue
                stamp = _stamp_s(message, log_time)
                if connection.topic != chosen:
                    a, w = message.linear_acceleration, message.angular_velocity
                    imu_rows.extend([(stamp, a.x, a.y, a.z, w.x, w.y, w.z)])
                    continue
                vector = message.magnetic_field
                pending.append((stamp, float(vector.x), float(vector.y), float(vector.z)))
                count += 1
                if len(pending) >= BLOCK_LINES:
                    mag_rows.extend(pending)
                    pending.clear()
                    if progress is not None:
                        progress(count, total)
            mag_rows.extend(pending)
            if progress is not None:
                progress(count, count)
    except RecordingError:
        raise
    except (ReaderError, OSError, ValueError, KeyError) as error:
        raise RecordingError(f'{path}: cannot read {kind} ({_one_line(error)})') from error
    table = mag_rows.result()
    keep = _usable(table[:, 1:], skipped)
    table = table[keep]
    skipped = Counter({reason: count for reason, count in skipped.items() if count})
    layout = f'topic {chosen}'
    accel = gyro = None
    notes: tuple[str, ...] = ()
    if imu_topic is not None:
        accel, gyro, paired = pair_by_stamp(table[:, 0], imu_rows.result())
        layout += f'; accelerometer topic {imu_topic}'
        notes = (f'{paired} of {len(table)} readings paired with a {imu_topic} sample within '
                 f'{PAIR_TOLERANCE_NS / 1e6:g} ms of their stamps'
                 + ('' if paired or not len(table) else
                    f': none, so nothing aligns (do {chosen} and {imu_topic} stamp by different '
                    'clocks, or was the Imu recorded at another time?)'),)
    extras: dict[str, object] = {}
    notes += side_notes
    if sides:
        extras, paired_notes = _paired_inputs(table[:, 0], sides, side_rows)
        notes += paired_notes
        layout += ''.join(f'; {kind} topic {name}' for name, kind in sides.items())
    return Recording(table[:, 1:].copy(), str(path), 'ROS 1 bag' if ros1 else 'rosbag2', layout,
                     dict(skipped), 'T', notes, accel=accel, gyro=gyro, stamps=table[:, 0].copy(),
                     time_source=f'header stamps of {chosen}', **extras)


def _input_topics(path: Path, topics: dict[str, str | None], battery: str | None,
                  temperature: str | None) -> tuple[dict[str, str], tuple[str, ...]]:
    """({topic: 'battery' | 'temperature'}, notes): the topics named, else the only one of each
    type (several: none, and a note names the option that chooses)."""
    chosen: dict[str, str] = {}
    notes: list[str] = []
    for wanted, msgtype, kind, option in ((battery, BATTERY_STATE, 'battery', '--battery-topic'),
                                          (temperature, TEMPERATURE_MSG, 'temperature',
                                           '--temperature-topic')):
        if wanted == '':
            continue
        if wanted is None:
            candidates = [name for name, kind_ in topics.items() if kind_ == msgtype]
            if len(candidates) > 1:
                notes.append(f'{len(candidates)} {msgtype} topics ({", ".join(candidates)}): '
                             f'none used; choose one with {option}')
            if len(candidates) != 1:
                continue
            chosen[candidates[0]] = kind
        else:
            chosen[_choose_topic(path, topics, wanted, msgtype, option)] = kind
    return chosen, tuple(notes)


def _side_value(message, log_time_ns: int) -> tuple[float, float]:  # noqa: ANN001
    """(stamp s, value) of a BatteryState (``current``, A) or Temperature (degrees Celsius)."""
    value = getattr(message, 'current', None)
    if value is None:
        value = getattr(message, 'temperature', math.nan)
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    return _stamp_s(message, log_time_ns), number


def _paired_inputs(stamps: np.ndarray, sides: dict[str, str],
                   rows: dict[str, list[tuple[float, float]]]
                   ) -> tuple[dict[str, object], tuple[str, ...]]:
    """Recording's inputs/temperature from the side topics' samples nearest each reading's stamp
    (the live tolerances), the notes and the problems (NaN, implausible, constant) counted."""
    from mag_calibrator_ros.calibration.live.compensation import (
        INPUT_TOLERANCE_NS,
        TEMPERATURE_TOLERANCE_NS,
    )
    extras: dict[str, object] = {}
    notes: list[str] = []
    problems: list[str] = []
    inputs, names = [], []
    for topic, kind in sides.items():
        samples = np.array(rows[topic], dtype=float).reshape(-1, 2)
        field_name = 'current' if kind == 'battery' else 'temperature'
        values, found = input_values(samples[:, 1], f'{topic} {field_name}', kind
                                     if kind == 'temperature' else 'input')
        problems += found
        tolerance = TEMPERATURE_TOLERANCE_NS if kind == 'temperature' else INPUT_TOLERANCE_NS
        usable = np.isfinite(values)
        paired = _nearest(stamps, samples[usable, 0], values[usable], tolerance * 1e-9)
        count = int(np.isfinite(paired).sum())
        notes.append(f'{count} of {len(stamps)} readings paired with a {topic} {field_name} '
                     f'within {tolerance / 1e9:g} s of their stamps')
        if not count:
            continue
        if kind == 'temperature':
            extras['temperature'] = paired
        else:
            inputs.append(paired)
            names.append(f'{topic}:{BATTERY_STATE}:current')
    if inputs:
        extras['inputs'] = np.column_stack(inputs)
        extras['input_names'] = tuple(names)
    extras['input_problems'] = tuple(problems)
    return extras, tuple(notes)


def _nearest(stamps: np.ndarray, times: np.ndarray, values: np.ndarray, tolerance_s: float
             ) -> np.ndarray:
    """For each stamp the value of the sample nearest it within the tolerance, else NaN."""
    out = np.full(len(stamps), math.nan)
    if len(times) == 0 or len(stamps) == 0:
        return out
    order = np.argsort(times, kind='stable')
    times, values = times[order], values[order]
    after = np.clip(np.searchsorted(times, stamps), 0, len(times) - 1)
    before = np.clip(after - 1, 0, len(times) - 1)
    nearest = np.where(np.abs(times[after] - stamps) < np.abs(stamps - times[before]),
                       after, before)
    close = np.abs(times[nearest] - stamps) <= tolerance_s
    out[close] = values[nearest[close]]
    return out


def is_ros1_bag(path: Path) -> bool:
    """A ROS 1 bag: named ``.bag`` (or any file starting with its ``#ROSBAG V2.0`` line)."""
    if path.suffix.lower() == ROS1_SUFFIX:
        return True
    try:
        with path.open('rb') as probe:
            return probe.read(len(ROS1_MAGIC)) == ROS1_MAGIC
    except OSError:
        return False


def _bag_topics(reader) -> dict[str, str | None]:  # noqa: ANN001 - either rosbags Reader
    return {connection.topic: connection.msgtype for connection in reader.connections}


def _stamp_s(message, log_time_ns: int) -> float:  # noqa: ANN001 - a deserialized message
    """The header stamp in seconds; the bag's receive time when a driver left it zero."""
    stamp = message.header.stamp
    seconds = stamp.sec + stamp.nanosec * 1e-9
    return seconds if seconds > 0.0 else log_time_ns * 1e-9


def pair_by_stamp(stamps: np.ndarray, imu: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(accel, gyro, paired): for each stamp (s), the (stamp, accel (3), gyro (3)) ``imu`` row
    nearest it within PAIR_TOLERANCE_NS, NaN rows where none is; as the node's ImuPairing does
    message by message."""
    accel = np.full((len(stamps), 3), math.nan)
    gyro = np.full((len(stamps), 3), math.nan)
    if len(imu) == 0 or len(stamps) == 0:
        return accel, gyro, 0
    imu = imu[np.argsort(imu[:, 0], kind='stable')]
    after = np.clip(np.searchsorted(imu[:, 0], stamps), 1, len(imu) - 1)
    before = after - 1
    if len(imu) == 1:
        nearest = np.zeros(len(stamps), dtype=int)
    else:
        nearest = np.where(np.abs(imu[after, 0] - stamps) < np.abs(stamps - imu[before, 0]),
                           after, before)
    close = np.abs(imu[nearest, 0] - stamps) <= PAIR_TOLERANCE_NS * 1e-9
    accel[close] = imu[nearest[close], 1:4]
    gyro[close] = imu[nearest[close], 4:7]
    return accel, gyro, int(np.count_nonzero(close))


def _usable(rows: np.ndarray, skipped: Counter[str]) -> np.ndarray:
    """Which rows are usable readings (finite, within MAX_READING); the others counted."""
    finite = np.all(np.isfinite(rows), axis=1)
    in_range = np.all(np.abs(rows) <= MAX_READING, axis=1)
    skipped['non_finite'] += int(np.count_nonzero(~finite))
    skipped['out_of_range'] += int(np.count_nonzero(finite & ~in_range))
    return in_range


def _choose_topic(path: Path, topics: dict[str, str | None], wanted: str | None,
                  msgtype: str = MAGNETIC_FIELD, option: str = '--topic') -> str:
    listing = ', '.join(f'{name} ({kind})' for name, kind in sorted(topics.items()))
    listing = listing or 'none'
    if wanted is not None:
        name = wanted if wanted in topics else '/' + wanted.lstrip('/')
        if name not in topics:
            raise RecordingError(f"{path}: no topic '{wanted}' in this bag; topics: {listing}")
        if topics[name] != msgtype:
            raise RecordingError(f"{path}: topic '{name}' is {topics[name]}, not {msgtype}")
        return name
    candidates = sorted(name for name, kind in topics.items() if kind == msgtype)
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise RecordingError(f'{path}: no {msgtype} topic in this bag; topics: {listing}')
    raise RecordingError(f'{path}: {len(candidates)} {msgtype} topics '
                         f'({", ".join(candidates)}); choose one with {option}')


def _one_line(error: BaseException) -> str:
    return ' '.join(str(error).split()) or type(error).__name__


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
