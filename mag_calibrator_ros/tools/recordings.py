# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Read magnetometer recordings into an ``(n, 3)`` float64 array for the offline fit.

Text (a file or ``-`` for stdin): CSV, TSV, whitespace or ``;`` separated, with or without a
header, LF or CRLF, and labelled lines such as ``Mx 144 My -270 Mz 415``. Each line is split into
*fields* on whitespace, ``,``, ``;`` and ``=``. Without ``columns`` the layout is detected from the
first lines: the most common pattern of numeric fields is the data; a header (or the labels in
the lines) naming the magnetometer's x, y, z picks those fields (``mx``, ``mag_x``, ``magX``,
``Bx``, ``Magnetic field x (µT)``, ``field.magnetic_field.x`` ..., see
:func:`recording_columns.column_roles`), and
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
the unit its values show (seconds or milliseconds, :func:`recording_time.time_unit`);
``Recording.time_source``
says which column and unit were taken. A log without one has ``stamps`` None: its rate is
unknown, and nothing that reads it may depend on a guessed one.

The robot's own field (``compensation``): a text log's current and temperature columns, by
header name (:func:`recording_inputs.compensation_columns`) or named; a bag's
``sensor_msgs/BatteryState``
(``current``) and ``sensor_msgs/Temperature`` topics, paired with each reading by stamp. A bad
value there (text, NaN, a temperature no sensor reads) is NaN in ``Recording.inputs`` /
``temperature``, counted and named in ``input_problems`` (a column that never varied too), and
never drops the reading.

Nothing is dropped silently: every skipped line or message is counted by reason in
``Recording.skipped`` (NaN/Inf, values beyond ``screening.MAX_READING``, ...). Problems a user
must fix raise ``RecordingError`` with a one-line message naming the source and what is wrong.
"""

from __future__ import annotations

from pathlib import Path
import sys
from typing import TextIO

from mag_calibrator_ros.tools.recording_bags import is_rosbag, read_rosbag
from mag_calibrator_ros.tools.recording_lines import STDIN
from mag_calibrator_ros.tools.recording_text import read_text, read_text_file
from mag_calibrator_ros.tools.recording_value import (
    ProgressCallback,
    Recording,
    RecordingError,
    describe_skips,
)


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
    either place finds them by name or type (``recording_inputs.compensation_columns``,
    ``recording_bags.read_rosbag``).

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
