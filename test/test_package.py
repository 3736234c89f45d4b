# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The package builds with colcon as an ament_python package and installs every console script."""

import os
from pathlib import Path
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

from catkin_pkg.package import parse_package
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
CONSOLE_SCRIPTS = (
    'icm20948_driver', 'mag_calibrator', 'mag_calibrator_fit', 'mag_calibrator_demo',
)


def test_package_xml_is_valid_for_catkin_pkg():
    # catkin_pkg rejects an invalid maintainer e-mail; colcon would then silently build the
    # package as plain Python and `ros2 run` would find nothing.
    warnings: list[str] = []
    package = parse_package(REPO_ROOT / 'package.xml', warnings=warnings)
    package.validate(warnings=warnings)
    assert package.name == 'mag_calibrator_ros' and package.package_format == 3
    assert warnings == []
    root = ElementTree.parse(REPO_ROOT / 'package.xml').getroot()
    assert root.find('export/build_type').text == 'ament_python'
    assert [license_.strip() for license_ in package.licenses] == ['MIT']  # OSI, as LICENSE
    import mag_calibrator_ros  # one version everywhere (QUALITY_DECLARATION.md, semver)

    assert f"version='{package.version}'" in (REPO_ROOT / 'setup.py').read_text()
    assert mag_calibrator_ros.__version__ == package.version


def test_every_dependency_is_a_rosdep_key_an_apt_user_of_jazzy_on_noble_resolves():
    """rosdistro review: each dependency resolves through rosdep on the target platform, and
    none by pip only (pip fails on noble's externally managed Python: the README's note). The
    keys come from a pinned ros/rosdistro commit (scripts/rosdep_keys.py, the first line)."""
    listed = (REPO_ROOT / 'test' / 'data' / 'rosdep_keys_noble_jazzy.txt').read_text()
    assert listed.startswith('# ros/rosdistro ')
    keys = {line for line in listed.splitlines()[1:] if line}
    package = parse_package(REPO_ROOT / 'package.xml')
    declared = {dependency.name for group in (
        package.buildtool_depends, package.build_depends, package.build_export_depends,
        package.exec_depends, package.test_depends, package.doc_depends)
        for dependency in group}
    assert 'rclpy' in declared and 'python3-numpy' in declared
    assert sorted(declared - keys) == []


def test_colcon_build_installs_console_scripts(tmp_path):
    colcon = shutil.which('colcon', path=str(Path(sys.executable).parent))
    if colcon is None:
        pytest.fail('colcon is not installed in the venv (requirements-dev.txt)')
    source = tmp_path / 'src' / 'mag_calibrator_ros'
    shutil.copytree(
        REPO_ROOT,
        source,
        ignore=shutil.ignore_patterns('.venv', '.git', 'build', 'install', 'log', '*.egg-info',
                                      '__pycache__', '.pytest_cache', '.hypothesis', 'out'),
    )
    env = dict(os.environ, COLCON_HOME=str(tmp_path / 'colcon_home'))
    result = subprocess.run(
        [colcon, 'build', '--base-paths', str(tmp_path / 'src'),
         '--build-base', str(tmp_path / 'build'), '--install-base', str(tmp_path / 'install'),
         '--event-handlers', 'console_direct-'],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    prefix = tmp_path / 'install' / 'mag_calibrator_ros'
    for script in CONSOLE_SCRIPTS:
        assert (prefix / 'lib' / 'mag_calibrator_ros' / script).is_file(), script
    share = prefix / 'share' / 'mag_calibrator_ros'
    assert (share / 'package.xml').is_file()
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
            / 'mag_calibrator_ros').is_file()
