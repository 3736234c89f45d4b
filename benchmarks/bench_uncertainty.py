#!/usr/bin/env python3
"""Is the covariance on every corrected message honest? (issue #45)

The simulated boards of ``bench_motions.py`` (``tumble`` added: the board tumbled by hand, 90 s)
are streamed through a default ``CalibrationSession`` as the node streams them. For every
corrected message from the first calibration on, the error ``e`` of the corrected field against
the true earth field in the body frame is compared with the published 1-sigma ``s`` of each
component (``Processed.uncertainty``, what the node puts on the covariance's diagonal):

- ``within 1s`` / ``within 2s``: the share of components with ``|e_i| <= s`` / ``2 s`` (68 % and
  95 % for an honest Gaussian 1-sigma);
- ``NEES``: the mean of ``|e|^2 / s^2`` (3 for an honest one; the issue's target: within 20 %);
- ``gross missed``: messages off by more than half the field whose error lies outside the
  99.7 % ellipsoid of their covariance (``|e|^2 > 14.16 s^2``).

    python benchmarks/bench_uncertainty.py [--seeds 3] [--cases tumble,wrist] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from bench_motions import BOARD, make_board, stream
import numpy as np

from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel
from mag_calibrator_ros.sim.config import SimConfig

CASES = ('tumble', 'wrist', 'drone', 'magnet', 'zone')
CHI2_3DOF_997 = 14.16


def board_of(case: str, seed: int) -> tuple[BoardModel, float]:
    if case == 'tumble':
        return BoardModel(SimConfig(seed=seed, **BOARD), motion.TumbleTrajectory(seed)), 90.0
    return make_board(case, seed)


def score(case: str, seed: int) -> dict[str, object]:
    errors, sigmas = [], []
    for _, processed, truth in stream(*board_of(case, seed)):
        if processed.corrected is not None:
            errors.append((np.asarray(processed.corrected) - truth) * 1e6)
            sigmas.append(processed.uncertainty * 1e6)
    if not errors:
        return {'case': case, 'seed': seed, 'messages': 0}
    e, s = np.array(errors), np.array(sigmas)
    nees = np.sum(e ** 2, axis=1) / s ** 2
    off = np.linalg.norm(e, axis=1) > 0.5 * BOARD['field_ut']
    return {'case': case, 'seed': seed, 'messages': len(e),
            'within_1s': float(np.mean(np.abs(e) <= s[:, None])),
            'within_2s': float(np.mean(np.abs(e) <= 2 * s[:, None])),
            'nees': float(np.mean(nees)), 'sigma_median_ut': float(np.median(s)),
            'gross': int(off.sum()), 'gross_missed': int(np.sum(nees[off] > CHI2_3DOF_997))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, default=3)
    parser.add_argument('--cases', default=','.join(CASES))
    parser.add_argument('--json')
    args = parser.parse_args(argv)
    rows = [score(case, seed) for case in args.cases.split(',') for seed in range(args.seeds)]
    print('| case | seed | messages | within 1σ | within 2σ | NEES (3) | median σ (µT) | '
          'gross missed |')
    print('|---|---|---|---|---|---|---|---|')
    for row in rows:
        if not row['messages']:
            print(f"| {row['case']} | {row['seed']} | 0 | – | – | – | – | – |")
            continue
        print(f"| {row['case']} | {row['seed']} | {row['messages']} | "
              f"{100 * row['within_1s']:.0f} % | {100 * row['within_2s']:.0f} % | "
              f"{row['nees']:.2f} | {row['sigma_median_ut']:.2f} | "
              f"{row['gross_missed']} of {row['gross']} |")
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as out:
            json.dump(rows, out, indent=1)
    return 0 if all(math.isfinite(r.get('nees', 0.0)) for r in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
