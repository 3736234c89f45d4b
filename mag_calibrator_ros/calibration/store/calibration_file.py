# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibration file: a ROS 2 parameters YAML, saved atomically, read bounded.

::

    /robot1/mag_calibrator:            # the saving node's fully qualified name (or /**, ...)
      ros__parameters:
        calibration:
          offset: [1.0e-06, -2.0e-06, 3.0e-06]
          matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]   # M, row-major
          rotation: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] # R, optional: identity
          field_strength: 5.0e-05
          model: "full"
          interference_inputs: ["battery_state:sensor_msgs/msg/BatteryState:current"]  # optional:
          interference: [8.0e-07, 0.0, 0.0]          # K (3 x k, row-major), tesla per unit
          temperature_coefficient: [2.0e-07, 0.0, 0.0]  # c, tesla per degC
          reference_temperature: 31.5                  # T0, degC
          residual_rms_pct: 0.8        # metadata: any further keys
          time: "2026-01-01T00:00:00Z"

The four compensation keys (``corrected = R M (raw - b - K u - c (T - T0))``, the robot's own
field: ``fit/calibration.py`` ``Compensation``) are optional: a file without them is the static
calibration it always was.

The same file is a ``--params-file`` for the node (the YAML is typed strictly:
``params_yaml``). A file may come from a user, another robot or an attacker: reading takes
regular files of at most ``MAX_FILE_BYTES`` only and parses within fixed limits (``safe_file``,
``params_yaml``), so a load of anything finishes in bounded time or fails with a
:class:`CalibrationFileError` naming the file and the problem. Saving is atomic, writes only a
regular file or a new path, and never writes what loading would refuse. Save and load share
:func:`resolve_calibration_path`.

The node works in tesla (REP-103). ``calibration.units`` says what the numbers are in: absent or
``T`` they are used as they are; another unit of magnetic flux density (``uT``, ``nT``, ``G``,
``mG`` ...: :data:`TESLA_PER_UNIT`) is converted to tesla when the calibration is built, so a
file ``mag_calibrator_fit`` wrote from a microtesla log loads right; anything else (``input``:
a recording's raw counts) is refused, because no scale to tesla is known.

The functions keep no state between calls and are thread-safe, so a node can run loads and saves
on a worker thread, off its message path.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.calibration import (
    MODELS,
    ROTATION_TOLERANCE,
    Calibration,
    CalibrationError,
    Compensation,
    calibration_problems,
    compensation_problems,
    rotation_problems,
)
from mag_calibrator_ros.calibration.fit.earth_field import TESLA_PER_UNIT
from mag_calibrator_ros.calibration.fit.input_sanity import (
    MAX_OFFSET_T,
    calibration_unit_problem,
    compensation_bound_problems,
)
from mag_calibrator_ros.calibration.store.params_yaml import (
    MAX_DEPTH,
    MAX_FILE_BYTES,
    MAX_NODES,
    NAME_TOKEN,
    ParamsYamlError,
    params_yaml,
    parse_params_yaml,
    short_repr,
)
from mag_calibrator_ros.calibration.store.safe_file import (
    FileAccessError,
    FileMissingError,
    read_regular_file,
    remove_stale_temporaries,
    resolve_path,
    shown_name,
    write_atomically,
)

DEFAULT_NODE_NAME = 'mag_calibrator'
SECTION = 'calibration'
REQUIRED_KEYS = ('offset', 'matrix', 'field_strength')
ROTATION_KEY = 'rotation'
UNITS_KEY = 'units'
TESLA = 'T'
COMPENSATION_KEYS = ('interference_inputs', 'interference', 'temperature_coefficient',
                     'reference_temperature')
RESERVED_KEYS = (*REQUIRED_KEYS, 'model', ROTATION_KEY, *COMPENSATION_KEYS)
FILE_MODELS = (*MODELS, 'identity')
"""Models a file may name: the fit models and 'identity' (:meth:`Calibration.identity`)."""
LEGACY_DEFAULT_PATH = '~/.ros/mag_calibrator/calibration.yaml'
"""The default file before per-node defaults; still read by ``/mag_calibrator`` (see
:func:`default_load_path`)."""
_COMMENTS = (
    'Magnetometer calibration: corrected = R @ M @ (raw - b - K u - c (T - T0)); M = matrix',
    '(row-major), b = offset, R = rotation (identity when absent), |corrected| ~ field_strength;',
    'K = interference (per interference_inputs), c = temperature_coefficient, T0 =',
    'reference_temperature (all optional: none is the static calibration).',
    'A ROS 2 parameters file (--params-file).',
)

__all__ = [
    'DEFAULT_NODE_NAME', 'FILE_MODELS', 'LEGACY_DEFAULT_PATH', 'MAX_DEPTH', 'MAX_FILE_BYTES',
    'MAX_NODES', 'ROTATION_TOLERANCE', 'CalibrationFileError', 'CalibrationFileMissingError',
    'LoadedCalibration',
    'calibration_from_parameters', 'calibration_yaml', 'default_calibration_path',
    'default_load_path', 'load_calibration', 'read_calibration_file', 'remove_stale_temporaries',
    'resolve_calibration_path', 'save_calibration', 'section_matches', 'tesla_per_unit',
    'try_read_calibration_file',
]


class CalibrationFileError(ValueError):
    """A calibration file cannot be read or written; the message names the file and the problem."""


class CalibrationFileMissingError(CalibrationFileError):
    """The calibration file does not exist: a first start, not a fault (no exists() race)."""


@dataclass(frozen=True)
class LoadedCalibration:
    """What :func:`read_calibration_file` found.

    ``sections``: the top keys the calibration came from (several matching sections are merged
    in file order, later values winning, exactly as ``--params-file`` merges them). ``notes``:
    things the user should know, e.g. a section written for another node, metadata dropped.
    """

    calibration: Calibration
    path: Path
    sections: tuple[str, ...]
    notes: tuple[str, ...] = ()


# -- paths and names ------------------------------------------------------------------------------


def resolve_calibration_path(path: str | os.PathLike[str]) -> Path:
    """The one path resolution of save and load: ``~`` expanded, absolute, symlinks followed.

    ``..`` is applied after symlinks (``os.path.realpath``; past a missing directory, to the name),
    so a save lands exactly where a load then looks. Raises :class:`CalibrationFileError`.
    """
    try:
        return resolve_path(path)
    except FileAccessError as error:
        raise CalibrationFileError(str(error)) from None


def default_calibration_path(fully_qualified_name: str) -> Path:
    """The node's own calibration file: ``$ROS_HOME/mag_calibrator/<namespace>__<name>.yaml``.

    ``/robot1/mag_calibrator`` -> ``~/.ros/mag_calibrator/robot1__mag_calibrator.yaml``,
    ``/mag_calibrator`` -> ``~/.ros/mag_calibrator/mag_calibrator.yaml`` (``ROS_HOME`` defaults to
    ``~/.ros``), so calibrators in different namespaces never share a file.
    """
    name = _fully_qualified(fully_qualified_name)
    ros_home = Path(os.environ.get('ROS_HOME') or '~/.ros').expanduser()
    return ros_home / 'mag_calibrator' / ('__'.join(name.strip('/').split('/')) + '.yaml')


def default_load_path(fully_qualified_name: str) -> Path:
    """The file to read at start-up when ``calibration_file`` is left at its default.

    The node's own :func:`default_calibration_path`; for ``/mag_calibrator`` (the single-robot
    set-up the old default served) the old shared :data:`LEGACY_DEFAULT_PATH` while its own file
    does not exist yet. Namespaced nodes never read the shared file: it may be another robot's.
    """
    own = default_calibration_path(fully_qualified_name)
    if _fully_qualified(fully_qualified_name) != '/' + DEFAULT_NODE_NAME:
        return own
    legacy = Path(LEGACY_DEFAULT_PATH).expanduser()
    try:
        if not own.exists() and legacy.is_file():
            return legacy
    except (OSError, ValueError):
        pass
    return own


def _fully_qualified(node_name: str) -> str:
    """``node_name`` as ``/namespace/name`` (a bare name is in the root namespace, as in rcl)."""
    if not isinstance(node_name, str) or not all(
        NAME_TOKEN.match(token) for token in node_name.removeprefix('/').split('/')
    ):
        raise CalibrationFileError(
            f'{node_name!r} is not a valid node name (letters, digits, _; optional /namespace/)'
        )
    return '/' + node_name.removeprefix('/')


def _check_section_key(key: str) -> None:
    """A top key rcl accepts: a node name, optionally with ``*`` / ``**`` tokens (``/**``)."""
    if not isinstance(key, str) or not all(
        token in ('*', '**') or NAME_TOKEN.match(token)
        for token in key.removeprefix('/').split('/')
    ):
        raise CalibrationFileError(
            f'{key!r} is not a valid node name (letters, digits, _; optional /namespace/; '
            f'* or ** wildcards)'
        )


def section_matches(key: str, fully_qualified_name: str) -> bool:
    """Whether ``--params-file`` applies section ``key`` to the node: rcl's rules.

    A key without a leading ``/`` is in the root namespace; ``*`` stands for one name token,
    ``**`` for any number (``/**`` matches every node, ``/**/mag_calibrator`` that name anywhere).
    """
    name = fully_qualified_name.removeprefix('/').split('/')
    matched = {0}  # how many tokens of the name the key's tokens so far can cover
    for token in key.removeprefix('/').split('/'):
        if token == '**':
            matched = set(range(min(matched), len(name) + 1)) if matched else set()
        else:
            matched = {n + 1 for n in matched if n < len(name) and token in ('*', name[n])}
    return len(name) in matched


# -- from parameter values ------------------------------------------------------------------------


def calibration_from_parameters(
    offset: ArrayLike,
    matrix: ArrayLike,
    field_strength: float,
    model: str = 'full',
    metadata: Mapping[str, Any] | None = None,
    rotation: ArrayLike | None = None,
) -> Calibration:
    """A :class:`Calibration` from parameter values (``--params-file`` or a loaded file).

    Integers are accepted wherever doubles are expected (``matrix: [1, 0, 0, ...]``,
    ``field_strength: 1``): a hand-written params file types them as integers. ``matrix`` is 9
    values row-major (or 3x3 nested). ``rotation`` (``calibration.rotation``; also taken from
    ``metadata['rotation']``, where the other ``calibration.*`` parameters arrive) must be a
    proper rotation (9 values row-major, orthonormal, det +1); absent means identity. Metadata
    keys that are not ROS parameter names are dropped (they could never be saved).
    ``metadata['units']`` other than tesla converts the calibration to tesla (and says ``T``)
    or is refused: :func:`tesla_per_unit`; numbers that cannot be tesla for a magnetometer are
    refused with the likely unit (``input_sanity.calibration_unit_problem``). Raises
    :class:`CalibrationError` naming every problem (type, shape, finiteness, definiteness, units).
    """
    problems: list[str] = []
    offset_values = _numbers(offset, 'offset', 3, problems)
    matrix_values = _numbers(matrix, 'matrix', 9, problems)
    strength = _number(field_strength, 'field_strength', problems)
    if not isinstance(model, str) or model not in FILE_MODELS:
        problems.append(f'model must be one of {", ".join(FILE_MODELS)}, got {short_repr(model)}')
    if metadata is not None and not isinstance(metadata, Mapping):
        problems.append(f'metadata must be a mapping, got {short_repr(metadata)}')
        metadata = None
    extra, _dropped = _savable_metadata(metadata or {})
    if ROTATION_KEY in extra:
        given = extra.pop(ROTATION_KEY)
        rotation = given if rotation is None else rotation
    rotation_values = None if rotation is None else _rotation(rotation, problems)
    compensation = _compensation(extra, problems)
    scale = 1.0
    if UNITS_KEY in extra:
        try:
            scale = tesla_per_unit(extra[UNITS_KEY])
        except ValueError as error:
            problems.append(str(error))
    if not problems:
        problems = calibration_problems(offset_values, np.reshape(matrix_values, (3, 3)), strength)
    if not problems:
        unit = calibration_unit_problem(np.array(offset_values) * scale, strength * scale)
        problems = [] if unit is None else [unit]
    if problems:
        raise CalibrationError('; '.join(problems))
    calibration = Calibration(
        np.array(offset_values), np.reshape(matrix_values, (3, 3)), strength, model, extra,
        None if rotation_values is None else np.reshape(rotation_values, (3, 3)), compensation,
    )
    if scale != 1.0:
        calibration = calibration.scaled(scale).with_metadata(**{UNITS_KEY: TESLA})
    if calibration.compensation is not None:
        problems = compensation_bound_problems(calibration.compensation, MAX_OFFSET_T)
        if problems:
            raise CalibrationError('; '.join(problems))
    return calibration


def _compensation(extra: dict[str, Any], problems: list[str]) -> Compensation | None:
    """The compensation keys taken out of ``extra`` (metadata), checked; None without them."""
    given = {key: extra.pop(key) for key in COMPENSATION_KEYS if key in extra}
    if not given:
        return None
    inputs = given.get('interference_inputs', [])
    if isinstance(inputs, str) or not isinstance(inputs, (list, tuple)) or not all(
            isinstance(name, str) and name for name in inputs):
        problems.append(f'interference_inputs must be a list of input names, got '
                        f'{short_repr(inputs)}')
        return None
    gains = given.get('interference')
    if gains is not None or inputs:
        gains = _numbers(gains if gains is not None else [], 'interference', 3 * len(inputs),
                         problems)
    drift = given.get('temperature_coefficient')
    if drift is not None:
        drift = _numbers(drift, 'temperature_coefficient', 3, problems)
    t0 = given.get('reference_temperature')
    if t0 is not None:
        t0 = _number(t0, 'reference_temperature', problems)
    if problems:
        return None
    wrong = compensation_problems(tuple(inputs), gains, drift, t0)
    if wrong:
        problems += wrong
        return None
    return Compensation(tuple(inputs), gains, drift, t0)


def tesla_per_unit(units: Any) -> float:
    """Tesla per unit of a calibration's ``units`` ('uT' -> 1e-6, 'T' -> 1).

    Raises ``ValueError`` for anything that is not a unit of magnetic flux density: numbers in
    a recording's own units ('input', 'counts') would be read as tesla, off by the sensor's
    scale (a raw-count offset of 222925 read as 222925 T), so such a file must be fitted again
    with the scale stated.
    """
    if isinstance(units, str) and units in TESLA_PER_UNIT:
        return TESLA_PER_UNIT[units]
    known = ', '.join(sorted({'T', 'mT', 'uT', 'nT', 'G', 'mG'}))
    raise ValueError(
        f'{SECTION}.{UNITS_KEY} is {short_repr(units)}, not a unit of magnetic field ({known}): '
        f"the numbers are in a recording's own units and the node works in tesla; fit again "
        f"with mag_calibrator_fit --units (the recording's unit) or --scale TESLA_PER_COUNT, "
        f'or set {SECTION}.{UNITS_KEY} to the unit the numbers are in'
    )


_REAL = (int, float, np.integer, np.floating)


def _number(value: Any, name: str, problems: list[str]) -> float:
    if isinstance(value, bool) or not isinstance(value, _REAL):
        problems.append(f'{name} must be a number, got {short_repr(value)}')
        return math.nan
    try:
        return float(value)
    except OverflowError:  # an integer beyond the double range
        problems.append(f'{name} is out of range: {short_repr(value)}')
        return math.nan


def _numbers(values: Any, name: str, count: int, problems: list[str]) -> list[float]:
    """``values`` as ``count`` finite floats (a 3x3 nested list counts as 9); problems appended."""
    if isinstance(values, np.ndarray):
        if values.size != count:
            problems.append(f'{name} must have {count} numbers, got {values.size}')
            return []
        values = values.reshape(-1).tolist()
    elif isinstance(values, Iterable) and not isinstance(values, (str, bytes, Mapping)):
        values = list(values)  # rclpy hands double arrays over as array.array('d')
    if isinstance(values, (list, tuple)) and values and all(
        isinstance(row, (list, tuple)) for row in values
    ):
        values = [value for row in values for value in row]
    if not isinstance(values, (list, tuple)):
        problems.append(f'{name} must be a list of {count} numbers, got {short_repr(values)}')
        return []
    if len(values) != count:
        problems.append(f'{name} must have {count} numbers, got {len(values)}')
        return []
    bad = [value for value in values if isinstance(value, bool) or not isinstance(value, _REAL)]
    if bad:
        problems.append(f'{name} must contain numbers only, got {short_repr(bad[0])}')
        return []
    numbers = [_number(value, name, problems) for value in values]
    if not all(math.isfinite(value) for value in numbers):
        problems.append(f'{name} has non-finite values: {numbers}')
        return []
    return numbers


def _rotation(value: Any, problems: list[str]) -> list[float]:
    """``calibration.rotation``: a proper rotation, row-major; R^T R = I and det R = +1."""
    values = _numbers(value, ROTATION_KEY, 9, problems)
    if not values:
        return []
    wrong = rotation_problems(values)
    problems += wrong
    return [] if wrong else values


def _savable_metadata(
    metadata: Mapping[Any, Any], prefix: str = f'{SECTION}.', depth: int = 0
) -> tuple[dict[str, Any], list[str]]:
    """Metadata without the entries a params file cannot hold, and their dotted names.

    A ROS parameter name token is letters, digits and ``_`` (not starting with a digit); any
    other key loads (rcl is lenient) but would make every later save fail, so it is dropped, as
    is nesting deeper than a file may hold.
    """
    kept: dict[str, Any] = {}
    dropped: list[str] = []
    for key, value in metadata.items():
        name = f'{prefix}{short_repr(key, 40) if not isinstance(key, str) else key[:40]}'
        if not isinstance(key, str) or not NAME_TOKEN.match(key):
            dropped.append(name)
        elif isinstance(value, Mapping):
            if depth >= MAX_DEPTH:
                dropped.append(name)
                continue
            kept[key], inner = _savable_metadata(value, f'{name}.', depth + 1)
            dropped += inner
        else:
            kept[key] = value
    return kept, dropped


def calibration_yaml(calibration: Calibration, node_name: str = DEFAULT_NODE_NAME) -> str:
    """The file's text: a ROS 2 parameters YAML whose top key is ``node_name``.

    ``node_name``: the node's fully qualified name (``/robot1/mag_calibrator``: what
    ``ros2 param dump`` writes, applied by ``--params-file`` to that node only), a wildcard key
    (``/**`` every node, ``/**/mag_calibrator`` that name in any namespace), or a bare name
    (``mag_calibrator``: rcl reads it as ``/mag_calibrator``, the root namespace only).
    Raises :class:`CalibrationFileError` for metadata no parameters file can hold.
    """
    _check_section_key(node_name)
    fields = _calibration_fields(calibration)
    try:
        return params_yaml(node_name, {SECTION: fields}, _COMMENTS)
    except ParamsYamlError as error:
        raise CalibrationFileError(str(error)) from None


def _calibration_fields(calibration: Calibration) -> dict[str, Any]:
    """The ``calibration`` section's values, in file order (metadata last)."""
    fields: dict[str, Any] = {
        'offset': [float(value) for value in calibration.offset],
        'matrix': [float(value) for value in calibration.matrix.reshape(9)],
        ROTATION_KEY: [float(value) for value in calibration.rotation.reshape(9)],
    }
    metadata = dict(calibration.metadata)
    for key in RESERVED_KEYS:
        if key in metadata:
            raise CalibrationFileError(f'metadata key {key!r} would overwrite the calibration')
    fields['field_strength'] = float(calibration.field_strength)
    fields['model'] = str(calibration.model)
    compensation = calibration.compensation
    if compensation is not None:
        if compensation.inputs:
            fields['interference_inputs'] = list(compensation.inputs)
            fields['interference'] = [float(value)
                                      for value in compensation.interference.reshape(-1)]
        fields['temperature_coefficient'] = [
            float(value) for value in compensation.temperature_coefficient]
        if compensation.reference_temperature is not None:
            fields['reference_temperature'] = compensation.reference_temperature
    fields.update(metadata)
    return fields


def calibration_parameters(calibration: Calibration) -> dict[str, Any]:
    """The calibration as the node's ``calibration.*`` parameters (dotted names), exactly what
    a saved file holds: ``ros2 param dump`` of the node then loads back with --params-file."""
    flat: dict[str, Any] = {}
    _flatten(_calibration_fields(calibration), f'{SECTION}.', flat)
    return flat


def save_calibration(
    path: str | os.PathLike[str], calibration: Calibration, node_name: str = DEFAULT_NODE_NAME
) -> Path:
    """Write the calibration file atomically, creating directories; returns the file written.

    ``node_name``: the top key (:func:`calibration_yaml`); pass the node's fully qualified name
    so ``--params-file`` applies the file to that node in its namespace. Only a regular file or
    a new path is written: a device node, FIFO, socket or directory at the path (or behind a
    symlink) is refused and left as it was. The text is checked to load back first. Temporary
    files of earlier interrupted saves of the same file are removed. Raises
    :class:`CalibrationFileError` naming the file and the problem.
    """
    target = resolve_calibration_path(path)
    shown = shown_name(path, target)
    try:
        text = calibration_yaml(calibration, node_name)
        _section_calibration(_parse(text, shown), '/' + DEFAULT_NODE_NAME, shown)
    except CalibrationFileError as error:
        raise CalibrationFileError(f'{shown}: cannot save: {error}') from None
    try:
        write_atomically(target, text.encode('utf-8'), shown)
    except FileAccessError as error:
        raise CalibrationFileError(str(error)) from None
    return target


# -- reading --------------------------------------------------------------------------------------


def load_calibration(
    path: str | os.PathLike[str], node_name: str = DEFAULT_NODE_NAME
) -> Calibration:
    """The calibration in a file, for node ``node_name``: :func:`read_calibration_file`."""
    return read_calibration_file(path, node_name).calibration


def read_calibration_file(
    path: str | os.PathLike[str], node_name: str = DEFAULT_NODE_NAME
) -> LoadedCalibration:
    """Read and validate a calibration file written by :func:`save_calibration` (or by hand).

    ``node_name``: the reading node's fully qualified name (a bare name is in the root
    namespace). The sections ``--params-file`` would apply to that node are used (its fully
    qualified name, ``/**``, ``/robot1/*`` ...; several are merged in file order). When none
    does, a file with exactly one calibration is still accepted — users copy files between
    robots and older versions keyed every file ``mag_calibrator:`` — and a note names the
    section; with several, the file is refused rather than one guessed. Parameters may be nested
    or dotted (``calibration.offset``), integers stand for doubles, ``calibration.rotation`` is
    optional. Everything under ``calibration`` other than the calibration keys comes back as
    metadata; keys that are not ROS parameter names are dropped with a note, so a loaded
    calibration always saves. Raises :class:`CalibrationFileError` saying which file and exactly
    what is wrong.
    """
    fully_qualified = _fully_qualified(node_name)
    resolved = resolve_calibration_path(path)
    shown = shown_name(path, resolved)
    try:
        data = read_regular_file(resolved, MAX_FILE_BYTES, shown)
    except FileMissingError as error:
        raise CalibrationFileMissingError(str(error)) from None
    except FileAccessError as error:
        raise CalibrationFileError(str(error)) from None
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError:
        raise CalibrationFileError(f'{shown}: not a text (UTF-8) file') from None
    calibration, sections, notes = _section_calibration(_parse(text, shown), fully_qualified,
                                                        shown)
    return LoadedCalibration(calibration, resolved, sections, notes)


def try_read_calibration_file(path: str | os.PathLike[str], node_name: str = DEFAULT_NODE_NAME
                              ) -> LoadedCalibration | Exception | None:
    """:func:`read_calibration_file` for a node, which reports and never raises: None when
    there is no file, any failure (of the file or of the calibration in it) as the exception."""
    try:
        return read_calibration_file(path, node_name)
    except CalibrationFileMissingError:
        return None
    except (CalibrationFileError, CalibrationError) as error:
        return error


def _parse(text: str, shown: str) -> Any:
    try:
        return parse_params_yaml(text)
    except ParamsYamlError as error:
        raise CalibrationFileError(f'{shown}: {error}') from None


# -- the calibration in a document ----------------------------------------------------------------


def _section_calibration(
    document: Any, fully_qualified: str, shown: str
) -> tuple[Calibration, tuple[str, ...], tuple[str, ...]]:
    """The calibration the document holds for the node, the sections used, and notes."""
    if document is None:
        raise CalibrationFileError(f'{shown}: the file is empty')
    if not isinstance(document, dict):
        raise CalibrationFileError(
            f'{shown}: expected a mapping of node names to ros__parameters, got a '
            f'{type(document).__name__}'
        )
    for key in document:
        try:
            _check_section_key(key)
        except CalibrationFileError as error:
            raise CalibrationFileError(
                f'{shown}: top key {error} (--params-file would refuse the file)'
            ) from None
    matching = [key for key in document if section_matches(key, fully_qualified)]
    notes: list[str] = []
    calibrated = {key: _calibration_parameters(document[key], key, shown, key in matching)
                  for key in document}
    calibrated = {key: parameters for key, parameters in calibrated.items() if parameters}
    used = [key for key in matching if key in calibrated]
    if not used:
        if len(calibrated) != 1:
            found = _listing(calibrated or document) or 'nothing'
            what = 'calibrations for' if calibrated else 'sections'
            raise CalibrationFileError(
                f'{shown}: no {SECTION} parameters for {fully_qualified} ({what} {found}'
                f'{"; keep the one to use" if len(calibrated) > 1 else ""})'
            )
        used = list(calibrated)
        notes.append(
            f'used section {used[0]!r}, written for another node (--params-file would not apply '
            f'it to {fully_qualified}; save again to rewrite it for this node)'
        )
    elif len(used) > 1:
        notes.append(f'merged sections {_listing(used)} in file order, as --params-file does')
    merged: dict[str, Any] = {}
    for key in used:
        merged.update(calibrated[key])
    section = _unflatten(merged, notes)
    missing = [key for key in REQUIRED_KEYS if key not in section]
    if missing:
        raise CalibrationFileError(
            f'{shown}: {SECTION} is missing {", ".join(f"{SECTION}.{key}" for key in missing)}'
        )
    metadata, dropped = _savable_metadata(  # the compensation's keys are taken out of it
        {key: value for key, value in section.items()
         if key not in RESERVED_KEYS or key in COMPENSATION_KEYS})
    if dropped:
        notes.append(f'dropped {_listing(dropped, quote=False)}: not ROS parameter names '
                     f'(letters, digits, _), they could never be saved')
    try:
        calibration = calibration_from_parameters(
            section['offset'], section['matrix'], section['field_strength'],
            section.get('model', 'full'), metadata, section.get(ROTATION_KEY),
        )
    except CalibrationError as error:
        raise CalibrationFileError(f'{shown}: {error}') from None
    units = metadata.get(UNITS_KEY, TESLA)
    if units != TESLA:
        notes.append(f'converted from {units} to tesla ({SECTION}.{UNITS_KEY}: {units!r}; '
                     f'x {tesla_per_unit(units):g})')
    return calibration, tuple(used), tuple(notes)


def _calibration_parameters(node: Any, key: str, shown: str, strict: bool) -> dict[str, Any]:
    """The section's ``calibration.*`` parameters, flat (``offset``, ``nested.a`` ...).

    ``strict`` (a section for this node): a malformed section is an error; otherwise it is
    simply not a calibration.
    """
    parameters = node.get('ros__parameters') if isinstance(node, dict) else None
    if not isinstance(parameters, dict):
        if strict:
            raise CalibrationFileError(f'{shown}: section {key!r} has no ros__parameters mapping')
        return {}
    flat: dict[str, Any] = {}
    _flatten(parameters, '', flat)
    prefix = SECTION + '.'
    section = {name[len(prefix):]: value for name, value in flat.items()
               if name.startswith(prefix)}
    if not section and strict and SECTION in flat:
        raise CalibrationFileError(
            f'{shown}: {key}.ros__parameters.{SECTION} must be a mapping of parameters, got '
            f'{short_repr(flat[SECTION])}'
        )
    return section


def _flatten(tree: Mapping[Any, Any], prefix: str, flat: dict[str, Any]) -> None:
    """ROS allows ``a: {b: 1}`` and ``a.b: 1`` alike: both become ``a.b``."""
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict) and value:
            _flatten(value, name + '.', flat)
        else:
            flat[name] = value


def _unflatten(flat: Mapping[str, Any], notes: list[str]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    clashes = []
    for name, value in flat.items():
        node = tree
        *parents, leaf = name.split('.')
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                break
        if not isinstance(node, dict) or isinstance(node.get(leaf), dict):
            clashes.append(f'{SECTION}.{name[:60]}')
            continue
        node[leaf] = value
    if clashes:
        notes.append(f'dropped {_listing(clashes, quote=False)}: clashes with a value of the '
                     f'same name')
    return tree


def _listing(names: Iterable[Any], quote: bool = True, shown: int = 5) -> str:
    """'a', 'b', 'c' and 4 more: a message names a few, never thousands."""
    names = list(names)
    text = ', '.join(short_repr(name, 40) if quote else str(name) for name in names[:shown])
    return text + (f' and {len(names) - shown} more' if len(names) > shown else '')
