#!/usr/bin/env bash
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
# Create the project venv with Python 3.11 (the ROS 2 Jazzy wheels on PyPI are cp311).
# On a fresh Debian/Ubuntu the venv module may be missing; install it when we are allowed to.
set -euo pipefail
venv=${1:-.venv}
if [ -x "$venv/bin/python" ] && "$venv/bin/python" -c 'import sys; assert sys.version_info[:2] == (3, 11)'; then
  exit 0
fi

python=""
for candidate in python3.11 python3; do
  if command -v "$candidate" >/dev/null 2>&1 &&
     "$candidate" -c 'import sys; raise SystemExit(sys.version_info[:2] != (3, 11))'; then
    python=$(command -v "$candidate")
    break
  fi
done
if [ -z "$python" ]; then
  echo "error: Python 3.11 is required (ROS 2 Jazzy wheels are built for CPython 3.11);" \
       "install python3.11 and retry." >&2
  exit 1
fi

apt_install() {
  local sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo -n"
  if command -v apt-get >/dev/null 2>&1; then
    DEBIAN_FRONTEND=noninteractive $sudo apt-get update -q &&
      DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q "$@"
  else
    return 1
  fi
}

if ! "$python" -m venv "$venv" 2>/dev/null; then
  rm -rf "$venv"
  echo "python venv module missing; installing python3.11-venv / python3-venv" >&2
  apt_install python3.11-venv || apt_install python3-venv || {
    echo "error: cannot create a venv; install the python3.11-venv package and retry." >&2
    exit 1
  }
  "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --disable-pip-version-check -q --upgrade pip
