# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The house's shape: each room imports only from the rooms below it, and no module imports
itself back through others (docs/ARCHITECTURE.md, "Rooms")."""

from __future__ import annotations

import ast
from pathlib import Path
import re

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


# -- the session's face (issue #43) --------------------------------------------------------------

SESSION = PACKAGE / 'calibration' / 'live' / 'session.py'
FACE_BOUND = 19
"""Public names of ``CalibrationSession`` at the most: its methods, properties and attributes."""
REACH = re.compile(r'(?<!live[/.])\bsession\.(?!py\b)([A-Za-z_]\w*)')
"""``session.<name>`` or ``.session.<name>``: how code outside the engine uses a session (not
the module: ``live.session.X``, ``session.py``)."""


def public_names(source: str, class_name: str) -> set[str]:
    """A class's public methods and properties, and every public ``self.<name>`` it assigns."""
    tree = ast.parse(source)
    cls = next(node for node in tree.body
               if isinstance(node, ast.ClassDef) and node.name == class_name)
    names = {node.name for node in cls.body
             if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)}
    for node in ast.walk(cls):
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, ast.AnnAssign | ast.AugAssign)
                   else [])
        names |= {target.attr for target in targets if isinstance(target, ast.Attribute)
                  and isinstance(target.value, ast.Name) and target.value.id == 'self'}
    return {name for name in names if not name.startswith('_')}


def _face() -> set[str]:
    return public_names(SESSION.read_text(), 'CalibrationSession')


def _reaches() -> list[str]:
    """Every ``session.<name>`` outside ``calibration/live/`` that is not on the face."""
    face = _face()
    paths = [path for path in (*PACKAGE.rglob('*.py'), *(PACKAGE.parent / 'test').rglob('*.py'),
                               *(PACKAGE.parent / 'benchmarks').rglob('*.py'))
             if 'calibration/live' not in path.as_posix() and path.name != 'test_house.py']
    found = []
    for path in paths:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            found += [f'{path.relative_to(PACKAGE.parent)}:{number}: session.{name}'
                      for name in REACH.findall(line) if name not in face]
    return found


def test_the_session_has_a_one_screen_face():
    face = _face()
    assert len(face) <= FACE_BOUND, sorted(face)


def test_nothing_outside_the_engine_reaches_into_the_session():
    assert _reaches() == []


HUB_LINES = {SESSION: 760, PACKAGE / 'nodes' / 'mag_calibrator.py': 610,
             PACKAGE / 'nodes' / 'icm20948_driver.py': 600}
"""The hubs stay readable (#43's bounds): what grows in them belongs in a room of its own."""


def test_the_hubs_stay_within_their_length():
    longer = {path.name: lines for path, bound in HUB_LINES.items()
              if (lines := len(path.read_text().splitlines())) > bound}
    assert longer == {}


def test_the_face_checks_see_a_grown_face_and_a_reach():
    grown = ('class CalibrationSession:\n    def __init__(self):\n'
             + ''.join(f'        self.part{i} = {i}\n' for i in range(FACE_BOUND))
             + '        self._private = 0\n    def process(self): ...\n'
             + '    @property\n    def state(self): ...\n')
    assert len(public_names(grown, 'CalibrationSession')) == FACE_BOUND + 2
    assert REACH.findall('x = node.session.buffer.fill + session._job') == ['buffer', '_job']
    assert REACH.findall('live.session.SessionSettings, live/session.py, session.py') == []
    assert {'process', 'report', 'calibration'} <= _face()


# -- the two tiers (conftest.ROS_FILES) ----------------------------------------------------------

ROS_MODULES = ('rclpy', 'launch', 'launch_ros', 'node_helpers', 'mag_calibrator_ros.tools.demo',
               'mag_calibrator_ros.nodes.mag_calibrator',
               'mag_calibrator_ros.nodes.icm20948_driver')
"""Importing one of these (or asking for it with importorskip) is starting a ROS graph."""


def starts_ros(source: str) -> bool:
    """Whether a test file's source starts a ROS graph: it imports rclpy, launch or a node
    (anywhere: in a test function too), or a test takes the ``ros`` fixture."""
    for node in ast.walk(ast.parse(source)):
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f'{node.module}.{alias.name}' for alias in node.names]
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == 'importorskip' and node.args
              and isinstance(node.args[0], ast.Constant)):
            names = [str(node.args[0].value)]
        elif isinstance(node, ast.FunctionDef) and node.name.startswith('test'):
            if 'ros' in {argument.arg for argument in node.args.args}:
                return True
        if any(name == module or name.startswith(module + '.')
               for name in names for module in ROS_MODULES):
            return True
    return False


def test_the_ros_tier_lists_every_file_that_starts_ros_and_only_those():
    from conftest import ROS_FILES

    tests = PACKAGE.parent / 'test'
    starting = {path.name for path in tests.glob('test_*.py') if starts_ros(path.read_text())}
    assert starting == set(ROS_FILES)


def test_the_tier_check_sees_ros_in_a_function_and_a_fixture():
    assert starts_ros('def test_a():\n    import rclpy\n')
    assert starts_ros('def test_b(ros, tmp_path):\n    pass\n')
    assert starts_ros("rclpy = pytest.importorskip('rclpy')\n")
    assert not starts_ros('import numpy\n# rclpy in a comment\n')


def test_every_source_file_names_the_licence_of_the_package():
    """REP-2004 / rosdistro review: a LICENSE file, the same licence in package.xml and
    setup.py, and a copyright and an SPDX line atop every Python and shell file tracked."""
    import subprocess

    root = PACKAGE.parent
    licence = re.search(r'<license>([^<]+)</license>', (root / 'package.xml').read_text())[1]
    assert licence == 'MIT' and (root / 'LICENSE').read_text().startswith('MIT License')
    assert f"license='{licence}'" in (root / 'setup.py').read_text()
    tracked = subprocess.run(['git', 'ls-files', '*.py', '*.sh', '.ci/run'], cwd=root,
                             capture_output=True, text=True, check=True).stdout.split()
    assert len(tracked) > 100
    heads = {name: ''.join((root / name).read_text().splitlines(keepends=True)[:3])
             for name in tracked}
    assert [name for name, head in heads.items()
            if f'SPDX-License-Identifier: {licence}' not in head
            or '# Copyright 2026 mag_calibrator_ros maintainers' not in head] == []
