# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Synthetic magnetometer recordings with known truth, for the engine benchmark.

Each scenario is a smooth hand-rotation trajectory (``motion.body_field_samples('tumble', ...)``)
seen through a distorted sensor::

    raw = S @ B_true + h + noise        (plus, for a few samples, a spike)

with ``S`` symmetric positive definite (soft iron: diagonal scale errors and cross terms) and ``h``
the hard-iron offset. Because ``S`` is symmetric, the ideal calibration ``M = S^-1`` (up to a scale
factor) makes the corrected field parallel to ``B_true``; the angle between them is the direction
error any calibration can be judged by, whatever its magnitude convention (F, 1 or fitted radius).
That is also the only part of the error a compass or AHRS cares about.

Calibrations are fitted on ``raw`` but judged on ``reading = S @ B_true + h``, the same samples
without noise and spikes: the per-sample noise alone (0.5 µT on 50 µT) puts ~0.8° of direction
error and ~1 % of magnitude spread on every sample whatever the calibration, which would hide the
0.1° differences the targets are about. What remains is the calibration's own error.

Spikes model transients (motor current, an I2C glitch): a random vector of 0.3-2 F added to a
random sample. No calibration can correct a spike, but a bad one lets spikes bend the fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mag_calibrator_ros.sim.motion import body_field_samples

FIELD_UT = 50.0
NOISE_UT = 0.5
SAMPLES = 3000
RATE_HZ = 50.0  # 3,000 samples = one minute of hand tumbling
SPIKE_RANGE = (0.3, 2.0)  # spike magnitude, in units of the field strength


@dataclass(frozen=True)
class Scenario:
    """One synthetic recording: what the sensor reported and what the field really was."""

    name: str
    raw: np.ndarray  # (n,3) µT, what a calibrator is fed
    reading: np.ndarray  # (n,3) µT, S @ truth + h: raw without noise and spikes (for judging)
    truth: np.ndarray  # (n,3) µT, true body-frame earth field per sample
    spikes: np.ndarray  # (n,) bool, samples carrying a spike outlier
    hard_iron: np.ndarray  # (3,) µT
    soft_iron: np.ndarray  # (3,3) symmetric positive definite S
    field_strength: float
    noise_ut: float
    seed: int


def random_soft_iron(
    rng: np.random.Generator, max_scale_error: float, max_off_diagonal: float
) -> np.ndarray:
    """A symmetric S: diagonal 1 +- ``max_scale_error``, off-diagonals up to the maximum.

    One off-diagonal term is pinned at +-``max_off_diagonal`` so every scenario contains the worst
    cross-coupling the issue names, not only a random share of it.
    """
    s = np.diag(1.0 + rng.uniform(-max_scale_error, max_scale_error, 3))
    upper = rng.uniform(-max_off_diagonal, max_off_diagonal, 3)
    upper[rng.integers(3)] = rng.choice([-1.0, 1.0]) * max_off_diagonal
    for value, (i, j) in zip(upper, ((0, 1), (0, 2), (1, 2)), strict=True):
        s[i, j] = s[j, i] = value
    if np.linalg.eigvalsh(s).min() <= 0.0:
        raise ValueError('soft-iron matrix is not positive definite; reduce the distortions')
    return s


def random_hard_iron(rng: np.random.Generator, magnitude: float) -> np.ndarray:
    """An offset of exactly ``magnitude`` in a random direction."""
    direction = rng.normal(size=3)
    return magnitude * direction / np.linalg.norm(direction)


def make_scenario(
    name: str,
    seed: int,
    hard_iron_ut: float,
    max_scale_error: float,
    max_off_diagonal: float,
    spike_fraction: float = 0.0,
    samples: int = SAMPLES,
    field_ut: float = FIELD_UT,
    noise_ut: float = NOISE_UT,
    rate_hz: float = RATE_HZ,
) -> Scenario:
    """Build one scenario, deterministic for ``seed``."""
    if not 0.0 <= spike_fraction < 1.0:
        raise ValueError(f'spike_fraction must be in [0, 1), got {spike_fraction}')
    rng = np.random.default_rng([seed, 20])
    inclination = rng.uniform(30.0, 70.0)
    truth = body_field_samples('tumble', samples, rate_hz, field_ut, inclination, seed)
    soft_iron = random_soft_iron(rng, max_scale_error, max_off_diagonal)
    hard_iron = random_hard_iron(rng, hard_iron_ut)
    reading = truth @ soft_iron.T + hard_iron
    raw = reading + rng.normal(0.0, noise_ut, truth.shape)
    spikes = np.zeros(samples, dtype=bool)
    spike_count = int(round(spike_fraction * samples))
    if spike_count:
        where = rng.choice(samples, size=spike_count, replace=False)
        spikes[where] = True
        directions = rng.normal(size=(spike_count, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        sizes = rng.uniform(*SPIKE_RANGE, spike_count) * field_ut
        raw[where] += directions * sizes[:, None]
    return Scenario(
        name=f'{name} s{seed}',
        raw=raw,
        reading=reading,
        truth=truth,
        spikes=spikes,
        hard_iron=hard_iron,
        soft_iron=soft_iron,
        field_strength=field_ut,
        noise_ut=noise_ut,
        seed=seed,
    )


# name -> (hard iron µT, max diagonal scale error, max off-diagonal, spike fraction)
SCENARIO_KINDS: dict[str, tuple[float, float, float, float]] = {
    'mild': (30.0, 0.03, 0.02, 0.0),
    'strong': (300.0, 0.10, 0.15, 0.0),
    'strong+1%spk': (300.0, 0.10, 0.15, 0.01),
    'strong+3%spk': (300.0, 0.10, 0.15, 0.03),
}


def standard_scenarios(
    seeds: tuple[int, ...] = (0, 1, 2), samples: int = SAMPLES
) -> list[Scenario]:
    """The benchmark set: every kind above for every seed."""
    return [
        make_scenario(name, seed, *parameters[:3], spike_fraction=parameters[3], samples=samples)
        for name, parameters in SCENARIO_KINDS.items()
        for seed in seeds
    ]


def direction_errors_deg(corrected: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Angle (degrees) between each corrected sample and the true field; NaN rows give NaN.

    ``atan2(|c x t|, c . t)`` stays accurate for the hundredths of a degree compared here, where
    ``arccos`` of a normalised dot product loses them to rounding.
    """
    corrected = np.asarray(corrected, dtype=float).reshape(-1, 3)
    truth = np.asarray(truth, dtype=float).reshape(-1, 3)
    cross = np.linalg.norm(np.cross(corrected, truth), axis=1)
    dot = np.einsum('ij,ij->i', corrected, truth)
    return np.degrees(np.arctan2(cross, dot))


def magnitude_spread_pct(corrected: np.ndarray) -> float:
    """std / mean of |corrected|, in percent: how far from a sphere the corrected cloud is."""
    magnitudes = np.linalg.norm(np.asarray(corrected, dtype=float).reshape(-1, 3), axis=1)
    mean = float(np.mean(magnitudes))
    if not np.isfinite(mean) or mean <= 0.0:
        return float('nan')
    return 100.0 * float(np.std(magnitudes)) / mean
