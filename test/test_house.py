"""The house's shape: each room imports only from the rooms below it, and no module imports
itself back through others (docs/ARCHITECTURE.md, "Rooms")."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'mag_calibrator_ros'

ROOMS = (
    'calibration.fit',
    'calibration.store',
    'icm20948',
    'calibration.live',
    'sim',
    'nodes',
    'tools',
)
"""Lowest first: a module may import from its own room and the rooms before it."""


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Every package module ``path`` imports, wherever the import stands (functions and
    TYPE_CHECKING blocks included)."""
    name = _module_name(path)
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                anchor = package.split('.')
                anchor = anchor[:len(anchor) - node.level + 1]
                base = '.'.join([*anchor, base] if base else anchor)
            targets = [base] + [f'{base}.{alias.name}' for alias in node.names]
        else:
            continue
        found |= {target for target in targets if target in modules}
    found.discard(name)
    return found


def _graph() -> dict[str, set[str]]:
    paths = sorted(PACKAGE.rglob('*.py'))
    modules = {_module_name(path) for path in paths}
    return {_module_name(path): _imports(path, modules) for path in paths}


def _room(module: str) -> int | None:
    relative = module.removeprefix('mag_calibrator_ros.')
    for index, room in enumerate(ROOMS):
        if relative == room or relative.startswith(room + '.'):
            return index
    return None


def test_every_module_lives_in_a_room():
    homeless = [module for module in _graph()
                if _room(module) is None and not module.endswith('__init__')
                and module not in ('mag_calibrator_ros', 'mag_calibrator_ros.calibration')]
    assert homeless == []


def test_no_room_imports_from_a_room_above_it():
    upward = [f'{module} -> {target}'
              for module, targets in _graph().items() if _room(module) is not None
              for target in targets
              if _room(target) is not None and _room(target) > _room(module)]
    assert upward == []


def test_no_import_circles():
    graph = _graph()
    circles = []
    state: dict[str, int] = {}  # 1 on the path, 2 done

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 1:
                circles.append(' -> '.join(path[path.index(target):] + [target]))
            elif target not in state:
                visit(target, [*path, target])
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert circles == []


def test_the_checks_see_an_upward_import_and_a_circle():
    """The graph is read from source: a fake pair of modules shows both defects."""
    assert _room('mag_calibrator_ros.calibration.fit.fitting') < _room(
        'mag_calibrator_ros.calibration.live.session')
    graph = _graph()
    assert 'mag_calibrator_ros.calibration.fit.calibration' in graph[
        'mag_calibrator_ros.calibration.fit.fitting']
    assert 'mag_calibrator_ros.calibration.live.jobs' in graph[
        'mag_calibrator_ros.calibration.live.worker']
