# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Online calibration tracking: gradient descent on ``(|m| - 1)^2``, generalised.

A. Sundqvist's notebook (2021, github.com/antsundq/Magnetometer-Auto-Calibration) learns a
diagonal model ``m = a * x + b`` sample by sample with
``a -= eta * 2 (1 - 1/|m|) m x`` and ``b -= eta * 2 (1 - 1/|m|) m``, either on raw input (its
``Simple_Model``, rate 1e-4) or on input divided by a magnitude (its ``Model``, rate 0.1). Here:

- the full model ``m = A (x / s - beta)``: ``A`` symmetric positive definite (soft iron with cross
  terms), ``beta`` the hard-iron offset; it starts from any :class:`Calibration` (identity, a fit,
  a file) and follows slow drift. ``corrected = F R m`` so ``M = F R A / s`` and ``b = s beta``,
  where ``R`` is the rotation part of a non-symmetric start matrix (polar decomposition), kept as
  given because a magnitude loss cannot see rotations (``R = I`` for the usual symmetric M);
- unit-free: ``s`` is the field radius in input units (from the starting calibration, or from the
  first sample when that calibration is grossly off-scale, as the notebook's ``Model`` does), so
  one learning rate serves T, µT, gauss and counts;
- the gradient is taken about the current offset (input centred on ``b``), which decouples the
  matrix from the offset; while the magnitude error is gross (> 20 % RMS) only the offset moves,
  because a magnitude-only loss has false minima (the cloud bent onto a cap or a huge sphere)
  that a free matrix falls into when the offset is several fields away;
- both update rules: ``normalise_input=False`` uses the centred input ``v`` as is (the notebook's
  rule), ``True`` divides it by its magnitude in the matrix step (the notebook's ``x / norm``
  taken per sample), which bounds that step whatever the offset or scale error;
- safe: non-finite, zero and degenerate samples are skipped; residuals beyond 5 % pull as 5 %
  (a Huber loss, once past the warm-up), so spikes barely move it; every step is bounded
  (``max_step``, relative to the field); a step that would give non-finite numbers or a matrix
  that is not well-conditioned positive definite is refused, so one bad sample never corrupts it.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.calibration import Calibration

DEFAULT_LEARNING_RATE = 0.01
"""Per-sample rate in field units. On 3,000-sample hand tumbles (1 % noise) it converges from an
identity start with a 6-field offset within about two such minutes and then holds ~0.1 deg RMS
direction error; 0.05 settles noisier (~0.2-0.3 deg), 0.005 is slower to start."""

DEFAULT_MAX_STEP = 0.02
"""Largest change per sample of the matrix (Frobenius) and of the offset, in field units: a spike
moves the calibration by at most 2 % of the field, and good samples pull it back."""

MAX_CONDITION = 100.0
"""A soft-iron matrix more anisotropic than 100:1 is not physical; such a step is refused."""

RESCALE_OUTSIDE = 10.0
"""If the first sample's |m| is off by more than this factor the starting calibration is in other
units (identity with F = 1 on µT data, say): the internal scale is taken from that sample."""

WARM_UP_RMS = 0.2
WARM_UP_MAX_STEPS = 1000
"""Until the RMS magnitude error falls below 20 % (or for at most 1000 steps, in case the field
strength itself is that wrong) only the offset is learnt."""

HUBER_RESIDUAL = 0.05

LOSS_SMOOTHING = 0.01  # EMA weight per sample: the loss is averaged over about 100 samples
WARM_UP_LOSS_CAP = 0.3**2  # per-sample loss caps of the health averages (see OnlineTracker)
SETTLED_LOSS_CAP = 0.1**2
CONVERGED_RMS = 0.05  # |m| within 5 % of the field, RMS, counts as converged
MIN_STEPS_FOR_CONVERGENCE = 100
_MIN_NORM = 1e-3  # |m| or |v| below this gives no usable gradient direction


@dataclass(frozen=True)
class TrackerHealth:
    """How the tracker is doing.

    ``loss``: EMA of ``(|m| - 1)^2`` (its square root is the RMS magnitude error relative to the
    field); ``converged``: enough steps and that RMS (each sample capped at 10 %, so spikes do
    not flip it) below 5 %; ``last_step``: size of the last parameter change in field units (it
    falls as the tracker settles).
    """

    steps: int
    skipped: int
    loss: float
    converged: bool
    refused_steps: int = 0
    last_step: float = 0.0
    rescaled: bool = False

    @property
    def rms_error(self) -> float:
        """RMS relative magnitude error, ``sqrt(loss)``."""
        return math.sqrt(self.loss) if math.isfinite(self.loss) else math.inf


TRACKING_MIN_SEPARATION_DEG = 6.0
"""A reading teaches the tracker only when its corrected direction is at least this far from the
last one that did (ArduPilot accepts samples about 6 deg apart). A robot standing still next to a
disturbance would otherwise pull the calibration toward fitting that one direction."""


def new_direction(corrected: np.ndarray, last: np.ndarray | None) -> np.ndarray | None:
    """The unit direction of a corrected reading when it points somewhere new: at least
    TRACKING_MIN_SEPARATION_DEG from ``last``, the direction that last taught the tracker
    (None when it is not new, or zero)."""
    norm = float(np.linalg.norm(corrected))
    if not norm > 0.0:
        return None
    corrected /= norm
    if last is not None and float(corrected @ last) > math.cos(
        math.radians(TRACKING_MIN_SEPARATION_DEG)
    ):
        return None
    return corrected


class OnlineTracker:
    """Gradient descent on ``(|M (x - b)| / F - 1)^2``, one sample at a time."""

    def __init__(
        self,
        calibration: Calibration,
        learning_rate: float = DEFAULT_LEARNING_RATE,
        normalise_input: bool = False,
        max_step: float = DEFAULT_MAX_STEP,
    ) -> None:
        if not (math.isfinite(learning_rate) and learning_rate > 0.0):
            raise ValueError(f'learning_rate must be positive and finite, got {learning_rate}')
        if not (math.isfinite(max_step) and max_step > 0.0):
            raise ValueError(f'max_step must be positive and finite, got {max_step}')
        self.learning_rate = float(learning_rate)
        self.normalise_input = bool(normalise_input)
        self.max_step = float(max_step)
        self._start = calibration
        # M = R P: the loss |R P v| = |P v| cannot see a rotation R, so R is kept as given and
        # only the symmetric positive definite P is learnt (R = I for the usual symmetric M).
        matrix = calibration.matrix
        if np.allclose(matrix, matrix.T, rtol=0.0, atol=1e-12 * np.abs(matrix).max()):
            self._rotation = np.eye(3)
            matrix = 0.5 * (matrix + matrix.T)
        else:
            import scipy.linalg  # only for a rotated start: 0.2 s off every node's start-up

            self._rotation, matrix = scipy.linalg.polar(matrix, side='right')
            matrix = 0.5 * (matrix + matrix.T)
        eigenvalues = np.linalg.eigvalsh(matrix)
        # Never more anisotropic than physical (or than the start, if that already is).
        self._max_condition = max(MAX_CONDITION, float(eigenvalues[-1] / eigenvalues[0]))
        # Internal units: s = field radius in input units, so A has determinant 1.
        geometric_mean = float(np.prod(eigenvalues)) ** (1.0 / 3.0)
        self._field = calibration.field_strength
        self._scale = self._field / geometric_mean
        self._a = matrix / geometric_mean
        self._beta = calibration.offset / self._scale
        self._steps = 0
        self._skipped = 0
        self._refused = 0
        self._loss = math.nan
        # The same EMA with each sample's loss capped, so spikes barely count: at 30 % error for
        # the warm-up test (which must see gross errors), at 10 % for the convergence test.
        self._warm_up_loss = math.nan
        self._settled_loss = math.nan
        self._last_step = 0.0
        self._rescaled = False
        self._cached: Calibration | None = calibration

    @property
    def calibration(self) -> Calibration:
        """The calibration tracked so far (model 'full'; the start's metadata kept)."""
        if self._cached is None:
            self._cached = Calibration(
                self._beta * self._scale,
                self._rotation @ self._a * (self._field / self._scale),
                self._field,
                model='full',
                metadata={**self._start.metadata, 'tracker_steps': self._steps},
                rotation=self._start.rotation,
            )
        return self._cached

    @property
    def health(self) -> TrackerHealth:
        loss = self._loss if math.isfinite(self._loss) else math.inf
        converged = (
            self._steps >= MIN_STEPS_FOR_CONVERGENCE
            and self._settled_loss <= CONVERGED_RMS * CONVERGED_RMS
        )
        return TrackerHealth(
            steps=self._steps,
            skipped=self._skipped,
            loss=loss,
            converged=converged,
            refused_steps=self._refused,
            last_step=self._last_step,
            rescaled=self._rescaled,
        )

    def update(self, raw: ArrayLike) -> bool:
        """Learn from one sample (3,); False when it was skipped or its step refused."""
        with np.errstate(all='ignore'):  # overflow in absurd input is caught as non-finite
            return self._update(raw)

    def _update(self, raw: ArrayLike) -> bool:
        try:
            x = np.asarray(raw, dtype=float).reshape(3)
        except (TypeError, ValueError):
            self._skipped += 1
            return False
        if not np.all(np.isfinite(x)) or not np.any(x):
            self._skipped += 1
            return False
        v = x / self._scale - self._beta  # centred, unit-free input
        m = self._a @ v
        norm_m = float(np.linalg.norm(m))
        norm_v = float(np.linalg.norm(v))
        if (
            self._steps == 0
            and math.isfinite(norm_m)
            and norm_m > 0.0
            and not 1.0 / RESCALE_OUTSIDE < norm_m < RESCALE_OUTSIDE
        ):
            self._rescale(norm_m)
            v = x / self._scale - self._beta
            m = self._a @ v
            norm_m = float(np.linalg.norm(m))
            norm_v = float(np.linalg.norm(v))
        if not (math.isfinite(norm_m) and norm_m > _MIN_NORM and norm_v > _MIN_NORM):
            self._skipped += 1
            return False
        residual = norm_m - 1.0
        warming_up = self._warming_up()
        # Huber: past 5 % a residual counts as 5 %, so a spike pulls no harder than a mild
        # disturbance (steps stay bounded by max_step as well). Not while warming up, where
        # every residual is large and the offset must travel.
        pull = residual if warming_up else min(max(residual, -HUBER_RESIDUAL), HUBER_RESIDUAL)
        gain = 2.0 * pull / norm_m  # dL/dm = gain * m
        direction = v / norm_v if self.normalise_input else v
        if warming_up:
            # Far from any sphere (offset still wrong): move the offset only, on a sphere of the
            # given radius. Letting the matrix move now would shrink or bend the cloud onto a
            # large sphere or a cap through it: false minima of a magnitude-only loss.
            step_a = np.zeros((3, 3))
        else:
            outer = np.outer(m, direction)
            step_a = -self.learning_rate * gain * 0.5 * (outer + outer.T)
        step_beta = self.learning_rate * gain * (self._a.T @ m)
        step_a *= min(1.0, self.max_step / max(float(np.linalg.norm(step_a)), 1e-300))
        step_beta *= min(1.0, self.max_step / max(float(np.linalg.norm(step_beta)), 1e-300))
        new_a = self._a + step_a
        new_beta = self._beta + step_beta
        if not (np.all(np.isfinite(new_a)) and np.all(np.isfinite(new_beta))):
            self._refused += 1
            return False
        eigenvalues = np.linalg.eigvalsh(new_a)
        if not (eigenvalues[0] > 0.0 and eigenvalues[-1] <= self._max_condition * eigenvalues[0]):
            self._refused += 1
            return False
        self._a, self._beta = new_a, new_beta
        self._cached = None
        self._steps += 1
        loss = residual * residual
        self._loss = _smoothed(self._loss, loss)
        self._warm_up_loss = _smoothed(self._warm_up_loss, min(loss, WARM_UP_LOSS_CAP))
        self._settled_loss = _smoothed(self._settled_loss, min(loss, SETTLED_LOSS_CAP))
        self._last_step = math.hypot(np.linalg.norm(step_a), np.linalg.norm(step_beta))
        return True

    def update_many(self, samples: ArrayLike) -> int:
        """Learn from samples (n, 3) in order; returns how many were used."""
        rows = np.asarray(samples, dtype=float).reshape(-1, 3)
        return sum(self.update(row) for row in rows)

    def _warming_up(self) -> bool:
        if self._steps >= WARM_UP_MAX_STEPS:
            return False
        return not self._warm_up_loss <= WARM_UP_RMS * WARM_UP_RMS

    def _rescale(self, norm_m: float) -> None:
        """Adopt the first sample's magnitude as the field radius (the notebook's ``norm_x``)."""
        self._scale *= norm_m
        self._beta = self._beta / norm_m
        self._rescaled = True


def _smoothed(average: float, value: float) -> float:
    """Exponential moving average; the first value starts it."""
    if not math.isfinite(average):
        return value
    return average + LOSS_SMOOTHING * (value - average)


class Tracking:
    """The online tracker of the calibration in force, started afresh with each one: it learns
    only from readings that point somewhere new (``new_direction``) and counts the steps that
    went in force."""

    def __init__(self) -> None:
        self.tracker: OnlineTracker | None = None
        self.updates = 0  # steps put in force (source 'tracking')
        self._last_taught: np.ndarray | None = None  # corrected direction that last taught it
        self._last_check: float | None = None

    def restart(self, calibration: Calibration | None, enabled: bool) -> None:
        self._last_taught = self._last_check = None
        self.tracker = None if calibration is None or not enabled else OnlineTracker(calibration)

    @property
    def calibration(self) -> Calibration | None:
        return None if self.tracker is None else self.tracker.calibration

    def teach(self, calibration: Calibration | None, reading: np.ndarray) -> None:
        """One reading that went to the buffer, when ``calibration`` corrects it somewhere new."""
        if self.tracker is None or calibration is None:
            return
        direction = new_direction(calibration.apply(reading), self._last_taught)
        if direction is not None:
            self._last_taught = direction
            self.tracker.update(reading)

    def checked(self, now: float) -> float | None:
        """Seconds since the previous check compared with the tracker (None: the first)."""
        last, self._last_check = self._last_check, now
        return None if last is None else now - last
