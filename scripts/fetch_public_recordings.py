#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Download the public recordings of test/data/public_recordings.json, each from its repository
at the pinned commit, into $MAG_PUBLIC_RECORDINGS (default ~/.cache/mag_calibrator_ros/
recordings), checking each file's sha256. They stay outside the repository (licences, size);
the tests and benchmarks that use them skip, naming this script, when they are absent.

    python scripts/fetch_public_recordings.py [--dir DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from pathlib import Path
import sys
import urllib.request

MANIFEST = Path(__file__).resolve().parents[1] / 'test' / 'data' / 'public_recordings.json'
DEFAULT_DIR = Path('~/.cache/mag_calibrator_ros/recordings').expanduser()


def recordings_dir() -> Path:
    """Where the public recordings live: $MAG_PUBLIC_RECORDINGS or the default cache."""
    return Path(os.environ.get('MAG_PUBLIC_RECORDINGS', DEFAULT_DIR)).expanduser()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--dir', type=Path, default=recordings_dir())
    args = parser.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    failed = 0
    for name, entry in json.loads(MANIFEST.read_text())['recordings'].items():
        target = args.dir / name
        if target.exists() and hashlib.sha256(target.read_bytes()).hexdigest() == entry['sha256']:
            print(f'{name}: present')
            continue
        url = (f"https://raw.githubusercontent.com/{entry['repository']}/{entry['commit']}/"
               f"{entry['path']}")
        try:
            with urllib.request.urlopen(url, timeout=60) as response:  # noqa: S310 - https only
                data = response.read()
        except OSError as error:
            print(f'{name}: cannot download {url} ({error})', file=sys.stderr)
            failed += 1
            continue
        if hashlib.sha256(data).hexdigest() != entry['sha256']:
            print(f'{name}: {url} does not match its sha256; not written', file=sys.stderr)
            failed += 1
            continue
        target.write_bytes(data)
        print(f"{name}: {len(data)} bytes from {entry['repository']} ({entry['licence']})")
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
