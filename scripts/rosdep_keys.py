#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Write the rosdep keys an apt user of ROS 2 Jazzy on Ubuntu noble can resolve, from a checkout
of ros/rosdistro (https://github.com/ros/rosdistro, Apache-2.0), for
test/test_package.py's check that every package.xml dependency is one of them:

    python scripts/rosdep_keys.py /path/to/rosdistro > test/data/rosdep_keys_noble_jazzy.txt

Kept: the system keys of rosdep/base.yaml and rosdep/python.yaml with an apt rule on noble (a
pip-only key fails rosdistro review, and pip fails on noble's externally managed Python), and
the ROS packages released into jazzy/distribution.yaml. The first lines name the commit.
"""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys

import yaml


def apt_on_noble(rule: object) -> bool:
    """Whether a rosdep rule installs something with apt on Ubuntu noble."""
    if not isinstance(rule, dict) or 'ubuntu' not in rule:
        return False
    ubuntu = rule['ubuntu']
    if isinstance(ubuntu, list):
        return bool(ubuntu)
    if not isinstance(ubuntu, dict):
        return False
    if 'pip' in ubuntu or 'source' in ubuntu:
        return False
    if 'apt' in ubuntu or 'packages' in ubuntu:
        return True
    release = ubuntu.get('noble', ubuntu.get('*'))
    if isinstance(release, dict):
        return 'pip' not in release and bool(release.get('packages', release.get('apt')))
    return bool(release)


def keys(checkout: Path) -> tuple[str, list[str]]:
    commit = subprocess.run(['git', '-C', str(checkout), 'log', '-1', '--format=%H %cs'],
                            capture_output=True, text=True, check=True).stdout.strip()
    names = set()
    for name in ('base.yaml', 'python.yaml'):
        rules = yaml.safe_load((checkout / 'rosdep' / name).read_text())
        names.update(key for key, rule in rules.items() if apt_on_noble(rule))
    distribution = yaml.safe_load((checkout / 'jazzy' / 'distribution.yaml').read_text())
    for repository, entry in distribution['repositories'].items():
        release = entry.get('release')
        if release:
            names.update(release.get('packages') or [repository])
    return commit, sorted(names)


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    commit, names = keys(Path(argv[1]))
    print(f'# ros/rosdistro {commit}: rosdep keys with an apt rule on Ubuntu noble, and the '
          'packages released into jazzy (scripts/rosdep_keys.py)')
    print('\n'.join(names))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
