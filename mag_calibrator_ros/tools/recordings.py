"""Read magnetometer recordings into an ``(n, 3)`` float64 array for the offline fit.

Text (a file or ``-`` for stdin): CSV, TSV, whitespace or ``;`` separated, with or without a
header, LF or CRLF, and labelled lines such as ``Mx 144 My -270 Mz 415``. Each line is split into
*fields* on whitespace, ``,``, ``;`` and ``=``. Without ``columns`` the layout is detected from the
first lines: the most common pattern of numeric fields wins and its first three numeric fields are
x, y, z (``Mx 144 My -270 Mz 415`` -> fields 1, 3, 5). ``columns`` chooses explicitly: three
**zero-based** field indices (``'1,3,5'`` picks 144, -270, 415 from that line) or three header
names (``'mx,my,mz'``).

rosbag2 (a bag directory, or a single ``.db3`` / ``.mcap`` file): the
``sensor_msgs/msg/MagneticField`` topic named by ``topic``, or the only such topic in the bag.
Values are tesla (REP-103).

Nothing is dropped silently: every skipped line or message is counted by reason in
``Recording.skipped``. Problems a user must fix raise ``RecordingError`` with a one-line message
naming the source and what is wrong.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
import itertools
from pathlib import Path
import re
import sys
from typing import TextIO

import numpy as np

from mag_calibrator_ros.calibration.fitting import LARGEST_READING

MAGNETIC_FIELD = 'sensor_msgs/msg/MagneticField'
BAG_SUFFIXES = ('.db3', '.mcap')
BINARY_CONTROL_FRACTION = 0.1
"""Share of control bytes in the first 4 KiB that marks a binary file (serial noise has fewer)."""
STDIN = '-'

FIELD_SEPARATORS = re.compile(r'[\s,;=]+')
COMMENT_PREFIXES = ('#', '%', '//')
LAYOUT_SAMPLE_LINES = 1000
"""Lines inspected to detect the layout (and find a header) before streaming the rest."""
PROGRESS_EVERY_LINES = 8192

SKIP_REASONS = {
    'header': 'header',
    'comment': 'comment',
    'wrong_field_count': 'field count differs from the data lines',
    'too_few_fields': 'too few fields for the chosen columns',
    'not_numeric': 'not numeric',
    'non_finite': 'NaN/Inf',
    'out_of_range': f'beyond ±{LARGEST_READING:.2g} (no reading in any unit)',
    'undecodable': 'undecodable message',
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
    """'text' or 'rosbag2'."""
    layout: str
    """Which fields or topic the samples came from, e.g. 'fields 1,3,5' or 'topic /imu/mag'."""
    skipped: dict[str, int] = field(default_factory=dict)
    units: str | None = None
    """Units implied by the format ('T' for bags); None when the file does not say."""
    notes: tuple[str, ...] = ()
    """Things the user should know, e.g. that more numeric fields were present than used."""

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


def parse_columns(spec: str) -> tuple[int, int, int] | tuple[str, str, str]:
    """Parse ``'1,3,5'`` (zero-based field indices) or ``'mx,my,mz'`` (header names)."""
    parts = [part.strip() for part in re.split(r'[,\s]+', spec.strip()) if part.strip()]
    usage = (f"bad --columns '{spec}': give three zero-based field indices such as 0,1,2 "
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
    min_rows: int = 1,
    stdin: TextIO | None = None,
    progress: ProgressCallback | None = None,
) -> Recording:
    """Read any supported recording; ``'-'`` reads text from ``stdin`` (default ``sys.stdin``).

    Raises ``RecordingError`` for missing or unreadable input, options that do not fit the input,
    no usable rows, or fewer than ``min_rows``.
    """
    if str(source) == STDIN:
        if topic is not None:
            raise RecordingError('--topic applies to rosbag2 input, not to text on stdin')
        recording = read_text(stdin if stdin is not None else sys.stdin, 'stdin',
                              columns=columns, progress=progress)
    else:
        path = Path(source)
        if is_rosbag(path):
            if columns is not None:
                raise RecordingError(f'{path}: --columns applies to text input, not to a rosbag2 '
                                     'bag (use --topic)')
            recording = read_rosbag(path, topic=topic, progress=progress)
        else:
            if topic is not None:
                raise RecordingError(f'{path}: --topic applies to rosbag2 input (a bag directory, '
                                     '.db3 or .mcap), not to a text file')
            recording = read_text_file(path, columns=columns, progress=progress)
    if recording.rows < max(min_rows, 1):
        found = 'no usable rows' if recording.rows == 0 else f'only {recording.rows} usable rows'
        skipped = f'; skipped {describe_skips(recording.skipped)}' if recording.skipped else ''
        need = f' (need at least {min_rows})' if min_rows > 1 else ''
        raise RecordingError(f'{recording.source}: {found} from {recording.layout}{need}{skipped}')
    return recording


def is_rosbag(path: Path) -> bool:
    """A bag directory (has metadata.yaml) or a storage file named .db3 / .mcap."""
    if path.is_dir():
        return True  # read_rosbag explains when it is not a bag
    return path.suffix.lower() in BAG_SUFFIXES


# --- text ------------------------------------------------------------------------------------


def read_text_file(
    path: Path, *, columns: str | None = None, progress: ProgressCallback | None = None,
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
            return _read_lines(stream, str(path), columns, progress, total)
    except OSError as error:
        raise RecordingError(f'{path}: cannot read ({error.strerror or error})') from error


def read_text(
    stream: TextIO, source: str = 'stdin', *, columns: str | None = None,
    progress: ProgressCallback | None = None,
) -> Recording:
    """Read a text recording from an open text stream (stdin, a StringIO ...)."""
    try:
        return _read_lines(stream, source, columns, progress, None)
    except UnicodeDecodeError as error:
        raise RecordingError(f'{source}: not text ({error.reason})') from error


def _refuse_binary(path: Path, head: bytes) -> None:
    if head.startswith(b'SQLite format 3\x00') or head.startswith(b'\x89MCAP'):
        raise RecordingError(f'{path}: looks like a rosbag2 storage file; name it .db3 or .mcap '
                             'or pass its bag directory')
    control = sum(byte < 9 or 13 < byte < 32 for byte in head)
    if control > BINARY_CONTROL_FRACTION * len(head):
        raise RecordingError(f'{path}: binary file, not a text recording or rosbag2 bag')


@dataclass(frozen=True)
class _Layout:
    """Which fields hold x, y, z; ``field_count`` set when every data line must have that many."""

    indices: tuple[int, int, int]
    field_count: int | None
    description: str
    notes: tuple[str, ...] = ()


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


def _detect_layout(lines: list[str], source: str) -> _Layout:
    """The most common pattern of numeric fields among the first lines; its first three."""
    patterns: Counter[tuple[int, tuple[int, ...]]] = Counter()
    for line in lines:
        if not line.strip() or _is_comment(line):
            continue
        tokens = _split(line)
        numeric = tuple(i for i, token in enumerate(tokens) if _number(token) is not None)
        if len(numeric) >= 3:
            patterns[(len(tokens), numeric)] += 1
    if not patterns:
        raise RecordingError(f'{source}: no line with three numeric fields in the first '
                             f'{len(lines)} lines (not a magnetometer recording?)')
    (field_count, numeric), _ = patterns.most_common(1)[0]
    indices = numeric[:3]
    notes = ()
    if len(numeric) > 3:
        notes = (f'lines have {len(numeric)} numeric fields; used fields '
                 f'{",".join(map(str, indices))} (choose others with --columns)',)
    return _Layout(indices, field_count, f'fields {",".join(map(str, indices))}', notes)


def _explicit_layout(spec: str, lines: list[str], source: str) -> _Layout:
    columns = parse_columns(spec)
    if isinstance(columns[0], int):
        indices = tuple(int(c) for c in columns)
        return _Layout(indices, None, f'fields {",".join(map(str, indices))}')  # type: ignore[arg-type]
    for line in lines:
        tokens = [token.lower() for token in _split(line)]
        if all(name in tokens for name in columns):
            indices = tuple(tokens.index(str(name)) for name in columns)
            return _Layout(indices, None, f'columns {",".join(map(str, columns))} '  # type: ignore[arg-type]
                           f'(fields {",".join(map(str, indices))})')
    raise RecordingError(f"{source}: no header line names all of --columns '{spec}' "
                         f'in the first {len(lines)} lines')


def _read_lines(
    stream: Iterable[str], source: str, columns: str | None,
    progress: ProgressCallback | None, total: int | None,
) -> Recording:
    lines = iter(stream)
    first = list(itertools.islice(lines, LAYOUT_SAMPLE_LINES))
    if columns is not None:
        layout = _explicit_layout(columns, first, source)
    elif not any(line.strip() for line in first):
        raise RecordingError(f'{source}: empty (no data lines)')
    else:
        layout = _detect_layout(first, source)
    rows, skipped = _parse(itertools.chain(first, lines), layout, progress, total)
    samples = np.array(rows, dtype=np.float64).reshape(-1, 3)
    return Recording(samples, source, 'text', layout.description, skipped, None, layout.notes)


def _parse(
    lines: Iterator[str], layout: _Layout, progress: ProgressCallback | None, total: int | None,
) -> tuple[list[tuple[float, float, float]], dict[str, int]]:
    rows: list[tuple[float, float, float]] = []
    skipped: Counter[str] = Counter()
    needed = max(layout.indices) + 1
    consumed = 0
    for count, line in enumerate(lines, start=1):
        consumed += len(line)
        if progress is not None and count % PROGRESS_EVERY_LINES == 0:
            progress(consumed, total)
        if not line.strip():
            continue
        if _is_comment(line):
            skipped['comment'] += 1
            continue
        tokens = _split(line)
        reason, row = _parse_line(tokens, layout, needed)
        if row is not None:
            rows.append(row)
        elif not rows and _is_text(tokens):
            skipped['header'] += 1
        else:
            skipped[reason] += 1
    if progress is not None:
        progress(consumed, total if total is not None else consumed)
    return rows, dict(skipped)


def _parse_line(
    tokens: list[str], layout: _Layout, needed: int,
) -> tuple[str, tuple[float, float, float] | None]:
    if layout.field_count is not None and len(tokens) != layout.field_count:
        return 'wrong_field_count', None
    if len(tokens) < needed:
        return 'too_few_fields', None
    values = [_number(tokens[i]) for i in layout.indices]
    if any(value is None for value in values):
        return 'not_numeric', None
    x, y, z = values
    if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
        return 'non_finite', None
    if max(abs(x), abs(y), abs(z)) > LARGEST_READING:
        return 'out_of_range', None
    return '', (x, y, z)  # type: ignore[return-value]


# --- rosbag2 ---------------------------------------------------------------------------------


def read_rosbag(
    path: Path, *, topic: str | None = None, progress: ProgressCallback | None = None,
) -> Recording:
    """Read ``magnetic_field`` of every message on a MagneticField topic of a rosbag2 bag."""
    from rosbags.rosbag2 import Reader, ReaderError
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise RecordingError(f'{path}: no such file or bag directory')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        raise RecordingError(f'{path}: a directory but not a rosbag2 bag (no metadata.yaml)')
    typestore = get_typestore(Stores.ROS2_JAZZY)
    rows: list[tuple[float, float, float]] = []
    skipped: Counter[str] = Counter()
    try:
        with Reader(path) as reader:
            chosen = _choose_topic(path, {name: info.msgtype for name, info in
                                          reader.topics.items()}, topic)
            info = reader.topics[chosen]
            total = info.msgcount or None
            count = 0
            for count, (connection, _, rawdata) in enumerate(
                    reader.messages(connections=info.connections), start=1):
                if progress is not None and count % PROGRESS_EVERY_LINES == 0:
                    progress(count, total)
                try:
                    vector = typestore.deserialize_cdr(rawdata, connection.msgtype).magnetic_field
                except Exception:  # noqa: BLE001 - a corrupt message is counted, not fatal
                    skipped['undecodable'] += 1
                    continue
                row = (float(vector.x), float(vector.y), float(vector.z))
                if not np.all(np.isfinite(row)):
                    skipped['non_finite'] += 1
                elif max(map(abs, row)) > LARGEST_READING:
                    skipped['out_of_range'] += 1
                else:
                    rows.append(row)
            if progress is not None:
                progress(count, count)
    except RecordingError:
        raise
    except (ReaderError, OSError, ValueError, KeyError) as error:
        raise RecordingError(f'{path}: cannot read rosbag2 bag ({_one_line(error)})') from error
    samples = np.array(rows, dtype=np.float64).reshape(-1, 3)
    return Recording(samples, str(path), 'rosbag2', f'topic {chosen}', dict(skipped), 'T')


def _choose_topic(path: Path, topics: dict[str, str | None], wanted: str | None) -> str:
    listing = ', '.join(f'{name} ({msgtype})' for name, msgtype in sorted(topics.items()))
    listing = listing or 'none'
    if wanted is not None:
        name = wanted if wanted in topics else '/' + wanted.lstrip('/')
        if name not in topics:
            raise RecordingError(f"{path}: no topic '{wanted}' in this bag; topics: {listing}")
        if topics[name] != MAGNETIC_FIELD:
            raise RecordingError(f"{path}: topic '{name}' is {topics[name]}, not {MAGNETIC_FIELD}")
        return name
    candidates = sorted(name for name, msgtype in topics.items() if msgtype == MAGNETIC_FIELD)
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise RecordingError(f'{path}: no {MAGNETIC_FIELD} topic in this bag; topics: {listing}')
    raise RecordingError(f'{path}: {len(candidates)} {MAGNETIC_FIELD} topics '
                         f'({", ".join(candidates)}); choose one with --topic')


def _one_line(error: BaseException) -> str:
    return ' '.join(str(error).split()) or type(error).__name__
