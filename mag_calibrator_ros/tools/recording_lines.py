# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Text read as bounded lines and fields, a block at a time, into growing float rows."""

from __future__ import annotations

from array import array
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
import re

import numpy as np

from mag_calibrator_ros.tools.recording_value import RecordingError

STDIN = '-'

BINARY_CONTROL_FRACTION = 0.1
"""Share of control bytes in the first 4 KiB that marks a binary file (serial noise has fewer)."""

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
