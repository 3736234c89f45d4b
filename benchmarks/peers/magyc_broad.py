#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""MAGYC (CoMPAS Lab, PyPI ``magyc``; Rodríguez-Martínez and Camilli, arXiv 2410.13827) on BROAD
trials: each method's soft iron and hard iron, as JSON, for ``benchmarks/bench_broad.py`` to
apply (``inv(soft_iron) @ (raw - hard_iron)``, MAGYC's own convention).

MAGYC needs numpy<2, gtsam and jax<0.5, which the project's venv does not hold, so it runs in a
venv of its own, and this script imports nothing of the package:

    python3.11 -m venv .venv-magyc && .venv-magyc/bin/pip install magyc==1.0.0
    .venv-magyc/bin/python benchmarks/peers/magyc_broad.py DIR/01_*.mat ... -o magyc.json

Every method sees every row of a trial (``--step N``: every N-th, for a quick look): the
magnetometer in µT, the gyroscope in rad/s, stamps from BROAD's sampling rate.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
import time
import warnings

import numpy as np
import scipy.io as spio

METHODS = ('magyc_ls', 'magyc_nls', 'magyc_bfg', 'magyc_ifg')


def calibrate(path: Path, methods: tuple[str, ...], step: int) -> dict:
    """Each method's calibration of one trial, or the error it raised."""
    import magyc  # noqa: PLC0415 - only in .venv-magyc

    data = spio.loadmat(path)
    mag = np.ascontiguousarray(data['imu_mag'][::step], dtype=float)
    gyr = np.ascontiguousarray(data['imu_gyr'][::step], dtype=float)
    rate = float(np.squeeze(data['sampling_rate'])) / step
    stamps = np.arange(len(mag)) / rate
    out = {}
    for name in methods:
        start = time.monotonic()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')
                result = getattr(magyc, name)(mag, gyr, stamps)
            hard, soft = np.asarray(result[0], float).ravel(), np.asarray(result[1], float)
            ok = bool(np.all(np.isfinite(hard)) and np.all(np.isfinite(soft)))
            out[name] = {'hard_iron': hard.tolist(), 'soft_iron': soft.tolist(),
                         'finite': ok}
        except Exception as error:  # noqa: BLE001 - a peer's failure is a result
            out[name] = {'error': f'{type(error).__name__}: {error}'}
        out[name]['seconds'] = round(time.monotonic() - start, 2)
        print(f'{path.stem} {name}: {out[name]["seconds"]} s', file=sys.stderr, flush=True)
    return {'rows': len(mag), 'step': step, 'methods': out}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('trials', nargs='+', type=Path, help='BROAD .mat files')
    parser.add_argument('-o', '--output', type=Path, required=True)
    parser.add_argument('--methods', default=','.join(METHODS))
    parser.add_argument('--step', type=int, default=1)
    args = parser.parse_args()
    methods = tuple(m for m in args.methods.split(',') if m)
    results = {}
    if args.output.exists():  # add to what an earlier run wrote
        results = json.loads(args.output.read_text())
    for path in args.trials:
        results[path.stem] = calibrate(path, methods, max(1, args.step))
        args.output.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
