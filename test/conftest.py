# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Test-wide settings: isolate ROS 2 traffic and locate the shared recordings."""

import atexit
import os
from pathlib import Path
import random
import shutil
import tempfile

from hypothesis import settings
import pytest

# Every test run gets its own DDS domain on localhost only, so parallel runs (CI, other sessions,
# a robot on the LAN) never see each other's topics. Must be set before rclpy.init(). pytest-xdist
# workers inherit the controller's domain; each takes the next one along, so no two of one run
# share a domain (ids 1..100: each fits Fast DDS's port range, localhost only).
os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(1, 100)))
_WORKER = os.environ.get('PYTEST_XDIST_WORKER', '')
if _WORKER.startswith('gw'):
    _base = int(os.environ['ROS_DOMAIN_ID'])
    os.environ['ROS_DOMAIN_ID'] = str((_base - 1 + int(_WORKER[2:])) % 100 + 1)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
# Nodes keep their calibration files under ROS_HOME: tests never touch the user's ~/.ros.
os.environ['ROS_HOME'] = tempfile.mkdtemp(prefix='mag_calibrator_tests_ros_home_')
atexit.register(shutil.rmtree, os.environ['ROS_HOME'], ignore_errors=True)

# CI explores the same examples every run (a failure there is reproducible, never a dice roll);
# local runs keep exploring new ones. No deadlines anywhere: speed lives in the benchmarks.
settings.register_profile('ci', derandomize=True, deadline=None, print_blob=True)
settings.register_profile('dev', deadline=None, print_blob=True)
settings.load_profile('ci' if os.environ.get('CI') else 'dev')

ROS_FILES = frozenset({
    'test_calibration_file_rclpy.py',  # rclpy --params-file: what rcl applies to which node
    'test_calibrator_node.py',
    'test_calibrator_node_first_day.py',
    'test_calibrator_node_imu.py',
    'test_calibrator_node_location.py',
    'test_calibrator_robustness.py',
    'test_compensation_node.py',
    'test_demo.py',  # the demo's nodes over DDS
    'test_driver_node.py',
    'test_ground_node.py',
    'test_launch.py',
    'test_launch_configs.py',
    'test_launch_shutdown.py',
    'test_view.py',
})
"""The test files that start a ROS graph (rclpy over DDS, ros2 launch): the ``ros`` tier.
``make test-core`` runs the rest, the default for an edit; ``make test`` runs both (CI).
test_house.py checks that every file that starts one is listed here."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in ROS_FILES:
            item.add_marker(pytest.mark.ros)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line('markers', 'ros: starts a ROS graph (rclpy over DDS, ros2 launch); '
                                       'deselect with -m "not ros" (make test-core)')


REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get('MAG_SHARED_DATA', REPO_ROOT.parent / 'shared' / 'data'))


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """The team's real recordings (../shared/data); never copied into the repository."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f'shared recordings not found at {SHARED_DATA} (set MAG_SHARED_DATA)')
    return SHARED_DATA


@pytest.fixture
def never_written(monkeypatch):
    """Fails a test at once if it gets as far as creating or renaming a file (tests that must
    never write through a device node, e.g. /dev/full, even when the code under test is wrong)."""

    def refuse(*args, **kwargs):
        raise AssertionError('a write was attempted')

    monkeypatch.setattr(tempfile, 'mkstemp', refuse)
    monkeypatch.setattr(os, 'replace', refuse)


@pytest.fixture(scope='module')
def ros():
    """One rclpy context a module, every node on its own thread (node_helpers.Ros); imported
    here, not at the top, so tests without ROS never load rclpy."""
    from node_helpers import Ros

    ros = Ros()
    yield ros
    ros.close()


PUBLIC_RECORDINGS = Path(os.environ.get(
    'MAG_PUBLIC_RECORDINGS', Path('~/.cache/mag_calibrator_ros/recordings').expanduser()))
"""Public recordings kept outside the repository (test/data/public_recordings.json lists them;
scripts/fetch_public_recordings.py downloads them here)."""
TEST_DATA = REPO_ROOT / 'test' / 'data'
"""Small real recordings committed with their provenance and licence (CI reads these)."""


@pytest.fixture(scope='session')
def public_recording():
    """``public_recording(name)``: the path of a fetched public recording, or a skip that says
    how to get it."""

    def find(name: str) -> Path:
        path = PUBLIC_RECORDINGS / name
        if not path.is_file():
            pytest.skip(f'{name} not in {PUBLIC_RECORDINGS}: run python '
                        'scripts/fetch_public_recordings.py (or set MAG_PUBLIC_RECORDINGS)')
        return path

    return find
