#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Does the magnetometer's noise bias the 3-D fits, or only spread them?

Stop 37 found the levelled planar fit pulled by the noise (about the noise squared) and mended it
with gradient-weighted residuals; its note asked whether the three 3-D models, which take their
magnitude residuals in corrected units, carry the same bias. Here each model fits readings of its
own kind of distortion (``sphere``: hard iron only; ``axis``: scales along the axes; ``full``:
symmetric soft iron with off-diagonals up to 0.12), 50 uT, hard iron up to 100 uT per axis, from
directions spread over the sphere, at each noise (uT per axis) and number of rows, ``--draws``
noise draws of the same truth for each of ``--cases`` truths:

- spread: the mean over draws of the direction error (RMS over 2000 noise-free directions) of
  each draw's calibration: what one calibration carries;
- bias: the same error of the calibration whose offset and matrix are the draws' means; the
  draws' spread still adds about spread / sqrt(draws) to it, shown beside it.

A bias grows as the noise squared and does not shrink with more rows; a spread grows as the
noise and shrinks as one over the root of the rows.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_noise_bias.py
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_noise_bias.py --models full --rows 3000
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_noise_bias.py --models axis --fit-as full
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration

FIELD_UT = 50.0


def unit_rows(count: int, rng: np.random.Generator) -> np.ndarray:
    rows = rng.normal(size=(count, 3))
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def distortion(model: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``raw = A h + b``, A of the model's kind."""
    if model == 'sphere':
        matrix = np.eye(3)
    elif model == 'axis':
        matrix = np.diag(rng.uniform(0.85, 1.15, 3))
    else:
        matrix = np.eye(3) + rng.uniform(-0.12, 0.12, (3, 3))
        matrix = (matrix + matrix.T) / 2
    return matrix, rng.uniform(-100.0, 100.0, 3)


def direction_rms_deg(calibration: Calibration, matrix: np.ndarray, offset: np.ndarray,
                      directions: np.ndarray) -> float:
    """Direction error of ``calibration`` on noise-free readings, after the best rotation (an
    ellipsoid fixes the soft iron only up to one; no IMU here to fix it)."""
    truth = FIELD_UT * directions
    corrected = calibration.apply(truth @ matrix.T + offset)
    left, _, right = np.linalg.svd(corrected.T @ truth)
    corrected = corrected @ (left @ right)
    cosines = np.sum(corrected * truth, axis=1) / (
        np.linalg.norm(corrected, axis=1) * FIELD_UT)
    return float(np.sqrt(np.mean(np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0))) ** 2)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--models', nargs='+', default=['sphere', 'axis', 'full'])
    parser.add_argument('--rows', type=int, nargs='+', default=[100, 3000])
    parser.add_argument('--noise', type=float, nargs='+', default=[0.5, 1.0, 2.0, 4.0])
    parser.add_argument('--draws', type=int, default=20)
    parser.add_argument('--cases', type=int, default=3)
    parser.add_argument('--fit-as', choices=['sphere', 'axis', 'full'],
                        help="fit every model's readings with this model instead of its own")
    args = parser.parse_args(argv)
    directions = unit_rows(2000, np.random.default_rng(99))
    print('| model | rows | noise uT | spread ° (mean, worst case) | bias ° (worst case) '
          '| spread / sqrt(draws) ° | failed |')
    print('|---|---:|---:|---|---:|---:|---:|')
    for model in args.models:
        for rows in args.rows:
            for noise in args.noise:
                spreads, biases, failed = [], [], 0
                for case in range(args.cases):
                    matrix, offset = distortion(model, np.random.default_rng(100 + case))
                    offsets, matrices, errors = [], [], []
                    for draw in range(args.draws):
                        rng = np.random.default_rng([case, draw, rows])
                        raw = (FIELD_UT * unit_rows(rows, rng)) @ matrix.T + offset
                        raw += noise * rng.normal(size=raw.shape)
                        result = fit_calibration(raw, FitOptions(model=args.fit_as or model))
                        if not result.success:
                            failed += 1
                            continue
                        fitted = result.calibration
                        offsets.append(fitted.offset)
                        matrices.append(fitted.matrix)
                        errors.append(direction_rms_deg(fitted, matrix, offset, directions))
                    if not errors:
                        continue
                    spreads.append(float(np.mean(errors)))
                    mean = Calibration(np.mean(offsets, axis=0), np.mean(matrices, axis=0),
                                       fitted.field_strength, model=fitted.model)
                    biases.append(direction_rms_deg(mean, matrix, offset, directions))
                if not spreads:
                    print(f'| {model} | {rows} | {noise:g} | — | — | — | {failed} |')
                    continue
                print(f'| {model} | {rows} | {noise:g} | {np.mean(spreads):.3f}, '
                      f'{max(spreads):.3f} | {max(biases):.3f} | '
                      f'{np.mean(spreads) / math.sqrt(args.draws):.3f} | {failed} |',
                      flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
