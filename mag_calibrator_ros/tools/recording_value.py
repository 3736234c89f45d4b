# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The ``Recording`` every reader returns, ``RecordingError``, and why rows were skipped."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mag_calibrator_ros.calibration.live.screening import MAX_READING

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
    'not_read': "listed in the bag's index but not read (damaged data: the reader stopped)",
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
