"""The calibration file: a ROS 2 parameters YAML (DESIGN.md §3), saved atomically, validated.

::

    mag_calibrator:
      ros__parameters:
        calibration:
          offset: [1.0e-06, -2.0e-06, 3.0e-06]
          matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]   # row-major
          field_strength: 5.0e-05
          model: "full"
          residual_rms_pct: 0.8        # metadata: any further keys
          time: "2026-01-01T00:00:00Z"

The same file is a ``--params-file`` for the node, so the writer is strict about YAML types:
every double carries a decimal point or an exponent (``1`` would be an integer and ROS refuses a
parameter whose type changes), every string is double-quoted (``on``, ``y``, ``1e5`` or ``0x10``
unquoted would become a bool or a number), and values YAML cannot type (None, empty lists) are
left out. Saving is atomic: a crash mid-write leaves the previous file as it was.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
import json
import math
import os
from pathlib import Path
import re
import tempfile
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
import yaml

from mag_calibrator_ros.calibration.calibration import (
    MODELS,
    Calibration,
    CalibrationError,
    calibration_problems,
)

DEFAULT_NODE_NAME = 'mag_calibrator'
SECTION = 'calibration'
REQUIRED_KEYS = ('offset', 'matrix', 'field_strength')
RESERVED_KEYS = (*REQUIRED_KEYS, 'model')
FILE_MODELS = (*MODELS, 'identity')
"""Models a file may name: the fit models and 'identity' (:meth:`Calibration.identity`)."""

_NAME_TOKEN = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')
_NODE_NAME = re.compile(r'^/?([A-Za-z_][A-Za-z0-9_]*/)*[A-Za-z_][A-Za-z0-9_]*$')
_INDENT = '  '


class CalibrationFileError(ValueError):
    """A calibration file cannot be read or written; the message names the file and the problem."""


# -- from parameter values ------------------------------------------------------------------------


def calibration_from_parameters(
    offset: ArrayLike,
    matrix: ArrayLike,
    field_strength: float,
    model: str = 'full',
    metadata: Mapping[str, Any] | None = None,
) -> Calibration:
    """A :class:`Calibration` from the node's parameter values (``matrix`` 9 values, row-major).

    Raises :class:`CalibrationError` naming every problem (shape, type, finiteness, definiteness).
    """
    problems = []
    offset_values = _numbers(offset, 'offset', 3, problems)
    matrix_values = _numbers(matrix, 'matrix', 9, problems)
    if isinstance(field_strength, bool) or not isinstance(field_strength, (int, float, np.number)):
        problems.append(f'field_strength must be a number, got {field_strength!r}')
        strength = math.nan
    else:
        strength = float(field_strength)
    if not isinstance(model, str) or model not in FILE_MODELS:
        problems.append(f'model must be one of {", ".join(FILE_MODELS)}, got {model!r}')
    if not problems:
        problems = calibration_problems(offset_values, np.reshape(matrix_values, (3, 3)), strength)
    if problems:
        raise CalibrationError('; '.join(problems))
    return Calibration(
        np.array(offset_values), np.reshape(matrix_values, (3, 3)), strength, model,
        dict(metadata or {}),
    )


def _numbers(values: Any, name: str, count: int, problems: list[str]) -> list[float]:
    """``values`` as ``count`` floats (a 3x3 nested list counts as 9); problems appended."""
    if isinstance(values, np.ndarray):
        values = values.tolist()
    elif isinstance(values, Iterable) and not isinstance(values, (str, bytes, Mapping)):
        values = list(values)  # rclpy hands double arrays over as array.array('d')
    if isinstance(values, (list, tuple)) and values and all(
        isinstance(row, (list, tuple)) for row in values
    ):
        values = [value for row in values for value in row]
    if not isinstance(values, (list, tuple)):
        problems.append(f'{name} must be a list of {count} numbers, got {values!r}')
        return []
    if len(values) != count:
        problems.append(f'{name} must have {count} numbers, got {len(values)}')
        return []
    bad = [value for value in values if isinstance(value, bool)
           or not isinstance(value, (int, float, np.number))]
    if bad:
        problems.append(f'{name} must contain numbers only, got {bad[0]!r}')
        return []
    numbers = [float(value) for value in values]
    if not all(math.isfinite(value) for value in numbers):
        problems.append(f'{name} has non-finite values: {numbers}')
        return []
    return numbers


# -- writing --------------------------------------------------------------------------------------


def calibration_yaml(calibration: Calibration, node_name: str = DEFAULT_NODE_NAME) -> str:
    """The file's text: a ROS 2 parameters YAML for node ``node_name``."""
    _check_node_name(node_name)
    fields: dict[str, Any] = {
        'offset': [float(value) for value in calibration.offset],
        'matrix': [float(value) for value in calibration.matrix.reshape(9)],
        'field_strength': float(calibration.field_strength),
        'model': str(calibration.model),
    }
    for key, value in calibration.metadata.items():
        if key in RESERVED_KEYS:
            raise CalibrationFileError(f'metadata key {key!r} would overwrite the calibration')
        fields[key] = value
    lines = [
        '# Magnetometer calibration: corrected = M @ (raw - b), M = matrix (row-major),',
        '# b = offset, |corrected| ~ field_strength. A ROS 2 parameters file (--params-file).',
        f'{node_name}:',
        f'{_INDENT}ros__parameters:',
        f'{_INDENT * 2}{SECTION}:',
    ]
    lines += _mapping_lines(fields, depth=3, path=SECTION)
    return '\n'.join(lines) + '\n'


def _mapping_lines(mapping: Mapping[str, Any], depth: int, path: str) -> list[str]:
    lines = []
    for key, value in mapping.items():
        if not isinstance(key, str) or not _NAME_TOKEN.match(key):
            raise CalibrationFileError(
                f'{path}: {key!r} is not a valid ROS parameter name (letters, digits, _)'
            )
        prefix = f'{_INDENT * depth}{key}:'
        if isinstance(value, Mapping):
            nested = _mapping_lines(value, depth + 1, f'{path}.{key}')
            if nested:
                lines += [prefix, *nested]
            continue
        scalar = _yaml_value(value)
        if scalar is not None:
            lines.append(f'{prefix} {scalar}')
    return lines


def _yaml_value(value: Any) -> str | None:
    """One parameter value as YAML text of an unambiguous type; None: not representable."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if value is None:
        return None
    if isinstance(value, (list, tuple)):
        items = [item.item() if isinstance(item, np.generic) else item for item in value]
        items = [item for item in items if item is not None]
        if not items:
            return None  # ROS cannot type an empty array
        if all(isinstance(item, bool) for item in items):
            return '[' + ', '.join(_scalar(item) for item in items) + ']'
        if all(isinstance(item, int) and not isinstance(item, bool) for item in items):
            return '[' + ', '.join(_scalar(item) for item in items) + ']'
        if all(isinstance(item, (int, float)) and not isinstance(item, bool) for item in items):
            return '[' + ', '.join(_double(float(item)) for item in items) + ']'
        return '[' + ', '.join(_quoted(str(item)) for item in items) + ']'
    return _scalar(value)


def _scalar(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return _double(value)
    return _quoted(str(value))


def _quoted(text: str) -> str:
    """A double-quoted YAML scalar: JSON escapes, plus \\u escapes for anything unprintable."""
    quoted = json.dumps(text, ensure_ascii=False)
    return ''.join(char if char.isprintable() else _escape(char) for char in quoted)


def _escape(char: str) -> str:
    code = ord(char)
    return f'\\u{code:04x}' if code <= 0xFFFF else f'\\U{code:08x}'


def _double(value: float) -> str:
    """A double YAML and ROS both read as a double: ``1.0``, ``5.0e-05``, ``.nan``, ``-.inf``."""
    if math.isnan(value):
        return '.nan'
    if math.isinf(value):
        return '.inf' if value > 0 else '-.inf'
    text = repr(value)  # always has a '.' or an 'e', and round-trips exactly
    if '.' not in text:
        text = text.replace('e', '.0e', 1)  # 1e-06 is a string to YAML 1.1; 1.0e-06 is not
    return text


def save_calibration(
    path: str | os.PathLike[str], calibration: Calibration, node_name: str = DEFAULT_NODE_NAME
) -> None:
    """Write the calibration file atomically, creating directories as needed.

    The text goes to a temporary file in the same directory, is flushed to disk, then renamed
    over the target (and the directory entry flushed), so readers see the old file or the new
    one, never a torn one. Raises :class:`CalibrationFileError` naming the file on any failure.
    """
    path = Path(path).expanduser()
    data = calibration_yaml(calibration, node_name).encode('utf-8')
    target = Path(os.path.realpath(path))  # through a symlink, replace what it points to
    temporary = None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        mode = target.stat().st_mode & 0o777 if target.exists() else 0o644
        descriptor, temporary = tempfile.mkstemp(
            prefix=f'.{target.name}.', suffix='.tmp', dir=target.parent
        )
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(descriptor, view):]
            os.fchmod(descriptor, mode)
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        os.replace(temporary, target)
        temporary = None
        _fsync_directory(target.parent)
    except OSError as error:
        raise CalibrationFileError(
            f'{path}: cannot write the calibration file: {error.strerror or error}'
        ) from error
    finally:
        if temporary is not None:
            try:
                os.unlink(temporary)
            except OSError:
                pass


def _fsync_directory(directory: Path) -> None:
    """Make the rename itself durable; some file systems cannot, which is not an error."""
    try:
        descriptor = os.open(directory, os.O_RDONLY | getattr(os, 'O_DIRECTORY', 0))
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def _check_node_name(node_name: str) -> None:
    if not isinstance(node_name, str) or not _NODE_NAME.match(node_name):
        raise CalibrationFileError(
            f'{node_name!r} is not a valid node name (letters, digits, _; optional /namespace/)'
        )


# -- reading --------------------------------------------------------------------------------------


def load_calibration(
    path: str | os.PathLike[str], node_name: str = DEFAULT_NODE_NAME
) -> Calibration:
    """Read and validate a calibration file written by :func:`save_calibration` (or by hand).

    Accepts the node's section as ``node_name``, ``/node_name`` or ``/**``, parameters nested or
    dotted (``calibration.offset``), integers where doubles are expected. Everything under
    ``calibration`` other than the four calibration keys comes back as metadata. Raises
    :class:`CalibrationFileError` saying which file and exactly what is wrong.
    """
    path = Path(path).expanduser()
    _check_node_name(node_name)
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise CalibrationFileError(f'{path}: no such file') from None
    except IsADirectoryError:
        raise CalibrationFileError(f'{path}: is a directory, not a calibration file') from None
    except UnicodeDecodeError:
        raise CalibrationFileError(f'{path}: not a text (UTF-8) file') from None
    except OSError as error:
        raise CalibrationFileError(f'{path}: cannot read: {error.strerror or error}') from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        where = getattr(error, 'problem_mark', None)
        line = f' at line {where.line + 1}, column {where.column + 1}' if where else ''
        problem = getattr(error, 'problem', None) or str(error)
        raise CalibrationFileError(f'{path}: not valid YAML{line}: {problem}') from None
    section = _calibration_section(document, node_name, path)
    missing = [key for key in REQUIRED_KEYS if key not in section]
    if missing:
        raise CalibrationFileError(
            f'{path}: {SECTION} is missing {", ".join(f"{SECTION}.{key}" for key in missing)}'
        )
    metadata = {key: value for key, value in section.items() if key not in RESERVED_KEYS}
    try:
        return calibration_from_parameters(
            section['offset'],
            section['matrix'],
            section['field_strength'],
            section.get('model', 'full'),
            metadata,
        )
    except CalibrationError as error:
        raise CalibrationFileError(f'{path}: {error}') from None


def _calibration_section(document: Any, node_name: str, path: Path) -> dict[str, Any]:
    """The ``calibration`` parameters of the node's section, as one nested mapping."""
    if document is None:
        raise CalibrationFileError(f'{path}: the file is empty')
    if not isinstance(document, dict):
        raise CalibrationFileError(
            f'{path}: expected a mapping with a {node_name!r} section, '
            f'got a {type(document).__name__}'
        )
    bare = node_name.lstrip('/')
    candidates = [key for key in (node_name, bare, '/' + bare, '/**') if key in document]
    if not candidates:
        found = ', '.join(repr(key) for key in document) or 'nothing'
        raise CalibrationFileError(f'{path}: no {bare!r} section (found {found})')
    node = document[candidates[0]]
    if not isinstance(node, dict) or not isinstance(node.get('ros__parameters'), dict):
        raise CalibrationFileError(
            f'{path}: section {candidates[0]!r} has no ros__parameters mapping'
        )
    parameters = _nested(node['ros__parameters'], path)
    section = parameters.get(SECTION)
    if not isinstance(section, dict):
        raise CalibrationFileError(
            f'{path}: no {SECTION} parameters under {candidates[0]}.ros__parameters'
        )
    return section


def _nested(parameters: dict[Any, Any], path: Path) -> dict[str, Any]:
    """ROS allows ``a: {b: 1}`` and ``a.b: 1`` alike; fold both into nested mappings."""
    tree: dict[str, Any] = {}
    for key, value in parameters.items():
        if not isinstance(key, str):
            raise CalibrationFileError(f'{path}: parameter name {key!r} is not a string')
        if isinstance(value, dict):
            value = _nested(value, path)
        node = tree
        *parents, leaf = key.split('.')
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise CalibrationFileError(f'{path}: parameter {key!r} clashes with a value')
        if isinstance(node.get(leaf), dict) and isinstance(value, dict):
            node[leaf].update(value)
        else:
            node[leaf] = value
    return tree
