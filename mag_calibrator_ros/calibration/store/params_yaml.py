# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ROS 2 parameters YAML as text, both ways, bounded: what rcl's ``--params-file`` reads.

Writing is strict about types, because rcl types a value by its text and refuses a parameter
whose type changes: every double carries a decimal point or an exponent (``1`` is an integer),
every string is double-quoted (``on``, ``y``, ``1e5`` or ``0x10`` unquoted would be a bool or a
number), arrays are of one type (rcl refuses ``[1, 2.5]``), and values rcl cannot type (None,
empty lists) are left out.

Reading refuses, before doing the work, what no parameters file needs and what makes YAML
expensive: anchors and aliases (a 1 kB "billion laughs" file expands to gigabytes), explicit
tags, nesting deeper than :data:`MAX_DEPTH`, more than :data:`MAX_NODES` values, texts longer than
:data:`MAX_FILE_BYTES`. Scalars are typed as rcl types them where PyYAML would differ or crash: a
date stays a string (``2026-13-45``), an integer beyond int64 is a double and a number beyond a
double stays text. No file system here: see ``safe_file``.
"""

from __future__ import annotations

from collections.abc import Mapping
import json
import math
import re
from typing import Any

import numpy as np
import yaml
from yaml.composer import Composer
from yaml.constructor import SafeConstructor
from yaml.events import AliasEvent
from yaml.parser import Parser
from yaml.reader import Reader
from yaml.resolver import Resolver
from yaml.scanner import Scanner

MAX_FILE_BYTES = 64 * 1024
"""Longest parameters text read or written (a calibration takes about 1 kB)."""
MAX_DEPTH = 16
"""Nesting levels of YAML collections (a calibration file uses 5)."""
MAX_NODES = 1000
"""YAML values in one text, keys included (a calibration uses about 100; a fleet file with the
calibrations of ten robots fits). Parsing time grows with it: it bounds a hostile text's."""

NAME_TOKEN = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')
"""One token of a ROS name or parameter name."""
INT64_RANGE = (-(2**63), 2**63 - 1)
_INDENT = '  '
_TIMESTAMP_TAG = 'tag:yaml.org,2002:timestamp'


class ParamsYamlError(ValueError):
    """The text is not a parameters YAML this package accepts, or a value cannot be written."""


def short_repr(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters: messages stay one readable line."""
    if isinstance(value, (list, tuple, Mapping)) and len(value) > limit:
        return f'a {type(value).__name__} of {len(value)} items'
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        return 'a very long integer'
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + '...'


# -- writing --------------------------------------------------------------------------------------


class _Budget:
    """Bounds the writer like the reader: a runaway value fails at once, not after gigabytes."""

    def __init__(self) -> None:
        self.lines = 0
        self.chars = 0

    def spend(self, line: str) -> str:
        self.lines += 1
        self.chars += len(line) + 1
        if self.lines > MAX_NODES or self.chars > MAX_FILE_BYTES:
            raise ParamsYamlError(
                f'too large for a parameters file (limits {MAX_NODES} values, '
                f'{MAX_FILE_BYTES} bytes)'
            )
        return line


def params_yaml(
    node_key: str, parameters: Mapping[str, Any], comments: tuple[str, ...] = ()
) -> str:
    """``node_key: {ros__parameters: parameters}`` as text rcl types exactly as given.

    Nested mappings become nested parameter names (``calibration: {offset: ...}`` is
    ``calibration.offset``). Raises :class:`ParamsYamlError` for names that are not parameter
    names and for values beyond the limits.
    """
    budget = _Budget()
    lines = [budget.spend(f'# {comment}') for comment in comments]
    lines += [budget.spend(f'{node_key}:'), budget.spend(f'{_INDENT}ros__parameters:')]
    lines += _mapping_lines(parameters, 2, '', budget)
    return '\n'.join(lines) + '\n'


def _mapping_lines(
    mapping: Mapping[str, Any], depth: int, path: str, budget: _Budget
) -> list[str]:
    if depth >= MAX_DEPTH or len(mapping) > MAX_NODES:
        raise ParamsYamlError(f'{path}: nested too deeply or too large to write')
    lines = []
    for key, value in mapping.items():
        if not isinstance(key, str) or not NAME_TOKEN.match(key):
            raise ParamsYamlError(
                f'{path}{"." if path else ""}{short_repr(key)} is not a valid ROS parameter '
                f'name (letters, digits, _)'
            )
        name = f'{path}.{key}' if path else key
        prefix = f'{_INDENT * depth}{key}:'
        if isinstance(value, Mapping):
            nested = _mapping_lines(value, depth + 1, name, budget)
            if nested:
                lines += [budget.spend(prefix), *nested]
            continue
        scalar = yaml_value(value, name)
        if scalar is not None:
            lines.append(budget.spend(f'{prefix} {scalar}'))
    return lines


def yaml_value(value: Any, name: str = 'value') -> str | None:
    """One parameter value as YAML text of an unambiguous type; None: not representable."""
    if isinstance(value, np.ndarray):
        if value.size > MAX_NODES:
            raise ParamsYamlError(f'{name}: {value.size} values are too many to write')
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if value is None:
        return None
    if isinstance(value, (list, tuple)):
        if len(value) > MAX_NODES:
            raise ParamsYamlError(f'{name}: {len(value)} values are too many to write')
        items = [item.item() if isinstance(item, np.generic) else item for item in value]
        items = [item for item in items if item is not None]
        if not items:
            return None  # ROS cannot type an empty array
        if all(isinstance(item, bool) for item in items):
            return '[' + ', '.join(_scalar(item, name) for item in items) + ']'
        if all(isinstance(item, int) and not isinstance(item, bool) for item in items):
            return '[' + ', '.join(_scalar(item, name) for item in items) + ']'
        if all(isinstance(item, (int, float)) and not isinstance(item, bool) for item in items):
            return '[' + ', '.join(double_text(_as_float(item, name)) for item in items) + ']'
        return '[' + ', '.join(_quoted(_text(item, name)) for item in items) + ']'
    return _scalar(value, name)


def _scalar(value: Any, name: str) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        if INT64_RANGE[0] <= value <= INT64_RANGE[1]:
            return str(value)
        return double_text(_as_float(value, name))  # what rcl makes of it: a double
    if isinstance(value, float):
        return double_text(value)
    return _quoted(_text(value, name))


def _as_float(value: float, name: str) -> float:
    try:
        return float(value)
    except OverflowError:
        raise ParamsYamlError(f'{name}: {short_repr(value)} is out of range') from None


def _text(value: Any, name: str) -> str:
    if isinstance(value, (list, tuple, Mapping, set)) and len(value) > MAX_NODES:
        raise ParamsYamlError(f'{name}: {len(value)} values are too many to write')
    text = value if isinstance(value, str) else str(value)
    if len(text) > MAX_FILE_BYTES:
        raise ParamsYamlError(f'{name}: a text of {len(text)} characters is too long')
    return text


def _quoted(text: str) -> str:
    """A double-quoted YAML scalar: JSON escapes, plus \\u escapes for anything unprintable."""
    quoted = json.dumps(text, ensure_ascii=False)
    return ''.join(char if char.isprintable() else _escape(char) for char in quoted)


def _escape(char: str) -> str:
    code = ord(char)
    return f'\\u{code:04x}' if code <= 0xFFFF else f'\\U{code:08x}'


def double_text(value: float) -> str:
    """A double YAML and ROS both read as a double: ``1.0``, ``5.0e-05``, ``.nan``, ``-.inf``."""
    if math.isnan(value):
        return '.nan'
    if math.isinf(value):
        return '.inf' if value > 0 else '-.inf'
    text = repr(value)  # always has a '.' or an 'e', and round-trips exactly
    if '.' not in text:
        text = text.replace('e', '.0e', 1)  # 1e-06 is a string to YAML 1.1; 1.0e-06 is not
    return text


# -- reading --------------------------------------------------------------------------------------


class _Refused(yaml.MarkedYAMLError):
    """YAML that is valid but not accepted in a parameters file (limits, anchors, tags)."""


class _BoundedComposer(Composer):
    """Composes the node tree within the limits; refuses anchors, aliases and explicit tags.

    Counting here stops a hostile text early, before the rest of it is even parsed.
    """

    def __init__(self) -> None:
        super().__init__()
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()
        if isinstance(event, AliasEvent) or getattr(event, 'anchor', None) is not None:
            raise _Refused(problem='YAML anchors and aliases (&name, *name) are not allowed',
                           problem_mark=event.start_mark)
        if getattr(event, 'tag', None) not in (None, '!'):
            raise _Refused(problem=f'explicit YAML tags ({event.tag}) are not allowed',
                           problem_mark=event.start_mark)
        self._nodes += 1
        if self._nodes > MAX_NODES:
            raise _Refused(problem=f'more than {MAX_NODES} values', problem_mark=event.start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Refused(problem=f'nested deeper than {MAX_DEPTH} levels',
                               problem_mark=event.start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


class _ParametersResolver(Resolver):
    """YAML 1.1 implicit types as rcl applies them.

    A date stays a string (``2026-13-45``: PyYAML would raise); ``1e-06`` is a double (YAML 1.1
    wants ``1.0e-06``, rcl reads it with strtod).
    """


_ParametersResolver.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != _TIMESTAMP_TAG]
    for first, resolvers in Resolver.yaml_implicit_resolvers.items()
}
_ParametersResolver.add_implicit_resolver(
    'tag:yaml.org,2002:float', re.compile(r'^[-+]?[0-9]+[eE][-+]?[0-9]+$'), list('-+0123456789')
)


class _ParametersConstructor(SafeConstructor):
    """Numbers as rcl types them: an integer beyond int64 is a double, beyond a double text."""

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int | float | str:
        text = str(self.construct_scalar(node))
        if len(text.replace('_', '')) > 24:  # longer than any int64: never int() 5,000 digits
            return _double_or_text(text)
        value = super().construct_yaml_int(node)
        in_range = INT64_RANGE[0] <= value <= INT64_RANGE[1]
        return value if in_range else _double_or_text(text)

    def construct_yaml_float(self, node: yaml.ScalarNode) -> float | str:
        text = str(self.construct_scalar(node))
        value = super().construct_yaml_float(node)
        if math.isinf(value) and '.inf' not in text.lower():
            return text  # overflows a double: rcl keeps the text
        return value


def _double_or_text(text: str) -> float | str:
    try:
        value = float(text.replace('_', ''))
    except ValueError:  # hexadecimal, octal or sexagesimal beyond int64
        return text
    return value if math.isfinite(value) else text


_ParametersConstructor.add_constructor(
    'tag:yaml.org,2002:int', _ParametersConstructor.construct_yaml_int)
_ParametersConstructor.add_constructor(
    'tag:yaml.org,2002:float', _ParametersConstructor.construct_yaml_float)


class _PythonLoader(Reader, Scanner, Parser, _BoundedComposer, _ParametersConstructor,
                    _ParametersResolver):
    """The pure-Python parser under the bounded composer (PyYAML without libyaml)."""

    def __init__(self, stream: str) -> None:
        Reader.__init__(self, stream)
        Scanner.__init__(self)
        Parser.__init__(self)
        _BoundedComposer.__init__(self)
        _ParametersConstructor.__init__(self)
        _ParametersResolver.__init__(self)


_Loader: type = _PythonLoader
if getattr(yaml, '__with_libyaml__', False):
    from yaml.cyaml import CParser

    class _LibyamlLoader(_BoundedComposer, CParser, _ParametersConstructor, _ParametersResolver):
        """libyaml's parser (C, faster than PyYAML's own) under the bounded composer in Python."""

        def __init__(self, stream: str) -> None:
            CParser.__init__(self, stream)
            _BoundedComposer.__init__(self)
            _ParametersConstructor.__init__(self)
            _ParametersResolver.__init__(self)

    _Loader = _LibyamlLoader


def parse_params_yaml(text: str, loader: type | None = None) -> Any:
    """The YAML document in ``text`` (None when empty), within the limits.

    Raises :class:`ParamsYamlError` with the line and column of the problem. ``loader`` is for
    tests (the pure-Python fallback).
    """
    if len(text) > MAX_FILE_BYTES:
        raise ParamsYamlError(f'longer than {MAX_FILE_BYTES} characters')
    parser = None
    try:
        parser = (loader or _Loader)(text)  # the pure-Python reader checks characters here
        return parser.get_single_data()
    except _Refused as error:
        raise ParamsYamlError(f'refused: {error.problem}{_where(error)}') from None
    except yaml.YAMLError as error:
        problem = getattr(error, 'problem', None) or str(error)
        raise ParamsYamlError(f'not valid YAML{_where(error)}: {problem}') from None
    except (ValueError, TypeError, ArithmeticError, RecursionError, MemoryError) as error:
        # the limits above should make these impossible; never let one escape as a crash
        raise ParamsYamlError(f'unreadable YAML: {short_repr(error, 120)}') from None
    finally:
        if parser is not None:
            parser.dispose()


def _where(error: yaml.YAMLError) -> str:
    mark = getattr(error, 'problem_mark', None)
    return f' at line {mark.line + 1}, column {mark.column + 1}' if mark is not None else ''
