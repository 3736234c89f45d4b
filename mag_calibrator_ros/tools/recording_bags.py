# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Read a rosbag2 or ROS 1 bag's MagneticField topic (its Imu, battery, temperature beside)."""

from __future__ import annotations

from collections import Counter
import math
from pathlib import Path

import numpy as np

from mag_calibrator_ros.calibration.live.pairing import PAIR_TOLERANCE_NS
from mag_calibrator_ros.calibration.live.screening import MAX_READING
from mag_calibrator_ros.tools.recording_inputs import input_values
from mag_calibrator_ros.tools.recording_lines import BLOCK_LINES, _GrowingRows
from mag_calibrator_ros.tools.recording_pairing import _nearest, pair_by_stamp
from mag_calibrator_ros.tools.recording_value import ProgressCallback, Recording, RecordingError

MAGNETIC_FIELD = 'sensor_msgs/msg/MagneticField'
IMU = 'sensor_msgs/msg/Imu'
BATTERY_STATE = 'sensor_msgs/msg/BatteryState'
TEMPERATURE_MSG = 'sensor_msgs/msg/Temperature'
BAG_SUFFIXES = ('.db3', '.mcap')
ROS1_SUFFIX = '.bag'
ROS1_MAGIC = b'#ROSBAG V2.0'


def is_rosbag(path: Path) -> bool:
    """A bag directory (has metadata.yaml), a storage file named .db3 / .mcap, or a ROS 1 bag."""
    if path.is_dir():
        return True  # read_rosbag explains when it is not a bag
    return path.suffix.lower() in BAG_SUFFIXES or is_ros1_bag(path)


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
            count = seen = 0
            for connection, log_time, rawdata in _messages(path, kind, reader, connections):
                seen += connection.topic == chosen
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
            skipped['not_read'] = max((total or 0) - seen, 0)  # damaged: the reader stopped
    except RecordingError:
        raise
    except (ReaderError, OSError, ValueError, KeyError) as error:
        raise RecordingError(f'{path}: cannot read {kind} ({_one_line(error)})'
                             + _repair_hint(error)) from error
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


def _messages(path: Path, kind: str, reader, connections: list):  # noqa: ANN001, ANN202
    """The reader's messages; whatever the reader itself raises while it reads the file (a
    damaged chunk: lz4's RuntimeError, zstd's ZstdError, bz2's OSError, a short read) is the
    file's fault, said in one line. Errors of the code reading each message are not caught
    here: they are bugs, not damaged files."""
    iterator = iter(reader.messages(connections=connections))
    while True:
        try:
            item = next(iterator)
        except StopIteration:
            return
        except Exception as error:  # noqa: BLE001 - any decompressor's own error type
            raise RecordingError(f'{path}: cannot read {kind}: damaged data in the file '
                                 f'({_one_line(error)})') from error
        yield item


UNINDEXED_HINT = ('; a recording stopped before rosbag wrote its index (a .bag.active file) '
                  'is made readable by `rosbag reindex FILE` on a ROS 1 machine (ROS 1 '
                  'rosbag: wiki.ros.org/rosbag/Commandline)')


def _repair_hint(error: BaseException) -> str:
    """How to repair what the reader refused, when there is a way ('' otherwise): rosbags
    reads no unindexed ROS 1 bag and its words name no tool a ROS 2 machine has."""
    return UNINDEXED_HINT if 'not indexed' in str(error) else ''


def _one_line(error: BaseException) -> str:
    return ' '.join(str(error).split()) or type(error).__name__
