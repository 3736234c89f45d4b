# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""A fixed-size buffer of well-spread magnetometer samples: a kNN uniqueness rule, fixed.

mag-calibrator-rs (P. Krull, 2023, github.com/peterkrull/mag-calibrator-rs) keeps N samples
and, once full, lets a new sample replace the buffered sample with the lowest mean distance to its
k nearest neighbours when the new sample's own mean k-NN distance is higher. Its flaws, and what
this module does instead:

- inconsistent scoring (buffered rows counted their zero self-distance, so every candidate won):
  every score here is the mean distance to k *other* points, the candidate's against the buffer;
- a manual pre-scaler and absolute thresholds: there are none, every decision compares distances
  with distances, so input in T, µT, gauss or counts gives the same decisions;
- an O(N² log N) recomputation per sample: each buffered point keeps its k nearest distances and
  indices; a sample that is not unique costs one O(N) distance pass, a replacement recomputes only
  the rows it touches (on average about 2k of them);
- duplicates and spikes: exact duplicates are refused, and once the buffer is given a reference
  calibration, samples off its surface are refused and buffered ones evicted. Spikes are the most
  "unique" samples of all, so without this they would be the last to leave.

The buffer stores, ranks and merges; it never fits and never decides when to. Its owner
(``session.CalibrationSession``) gives it a reference -- a
full fit of the buffer itself, or the calibration in force -- with the tolerance to screen by,
and takes it away when it no longer describes the sensor. With a reference that may merge (a full
fit of the buffer):

- merging: a sample that is not unique adds its information to its nearest buffered point
  instead of being dropped: each point keeps the count, sum and second moment of the readings it
  stands for (``counts``: fit with them as weights), and a replaced point's readings join its
  nearest neighbour. A fit of N single readings cannot beat the Cramér-Rao bound of N readings;
  merged points carry every reading's information. A plain mean of readings spread over a patch
  of a curved surface lies inside it (by d²/2R over a patch of size d), so ``samples`` places each
  mean back on the surface along its direction, using the readings' spread and the latest
  reference (second order, see ``_MagnitudeScreen.on_surface_mean``). Placing them at read time
  rather than when merging means an early, rougher reference bends nothing for good. The buffered
  point keeps its original position (its *anchor*) for the uniqueness rule, which is unchanged.

Each reading may carry an opaque *state* (``add``): the owner's record of what was taken off
it before it got here (the robot's own field, ``live/compensation.py``), linear, so a merged
point keeps the mean of its readings' states. When what is taken off changes, ``shift`` moves
every point and recent reading by what the owner computes from those states, instead of
forgetting them.

Input must already be screened (finite, not all-zero, not saturated): see
:mod:`~mag_calibrator_ros.calibration.live.screening`. Memory is fixed: every array is
allocated once for the configured capacity.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import math
import random

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import Coverage, direction_coverage

OUTCOMES = ('added', 'replaced', 'not_unique', 'duplicate', 'magnitude_outlier')
"""Everything :meth:`SampleBuffer.add` can return; the last two are refusals."""

DEFAULT_CAPACITY = 100
"""About ten samples per parameter of the full model (offset 3 + symmetric matrix 6), small enough
that adding a sample stays light enough for the message path and a fit stays short."""

DEFAULT_K = 6
"""The six nearest neighbours are the first ring around a point on an evenly covered sphere, so
the score measures local crowding rather than the distance to one twin (benchmarks/bench_engine.py
compares k = 2 to 8; the differences are small and 6 was best)."""

DEFAULT_MAGNITUDE_TOLERANCE = 0.3
"""A sample whose corrected magnitude is off the reference field by more than 30 % is a gross
outlier (a spike or a magnet nearby). Good data under a calibration that passed the fit gates stays
within a few per cent, so this never rejects it."""

READING_SAMPLE_SIZE = 256
"""Readings kept as a random draw of the recent stream (``readings``): the evidence that the
buffer's shell is the field sphere and not the rim of a still sensor's noise (see
coverage.shell_directions). 256 tell a share of one half to within about 3 %."""

PAIRED_SAMPLE_SIZE = 1024
"""Readings that came paired with the accelerometer, kept with gravity's direction as a random
draw of the same recent stream (``paired_readings``): what a ground robot's turn is levelled by
(levelled.py). The vertical field shows there only through tilts of a degree or two, so it takes
many readings: a quarter as many doubled the heading error in benchmarks/bench_ground.py."""

READING_HORIZON = 2048
"""The draw favours the last ~2,048 readings (each survives a geometric time of that mean), so
after a change (a re-mounted sensor, a moved magnet) it soon describes the new situation."""

_UPPER = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])  # 3x3 from the stored upper triangle
_TRIU = np.triu_indices(3)
_CHUNK_ROWS = 64  # rows per block when recomputing many neighbour lists: bounded temporaries


class SampleBuffer:
    """Keeps the ``capacity`` most spread-out samples seen so far.

    ``add`` returns what happened: 'added' (buffer not yet full), 'replaced', 'not_unique'
    (merged into its nearest point when a reference exists), 'duplicate' or 'magnitude_outlier'.
    """

    def __init__(self, capacity: int = DEFAULT_CAPACITY, k: int = DEFAULT_K) -> None:
        capacity, k = _checked_size(capacity, k)
        self._state_size = 0  # see forget_states
        self._allocate(capacity, k)
        self._seen = 0
        self.evicted = 0
        """Buffered samples removed because a new reference showed them to be outliers."""
        self.merged = 0
        """Samples that were not unique and were folded into their nearest buffered point."""
        self._reference: _MagnitudeScreen | None = None  # set_reference(): screens
        self._merging = False  # the reference may also merge (a full fit of the buffer itself)
        self._projection: _MagnitudeScreen | None = None  # the latest that merged: places means
        self._readings = np.zeros((READING_SAMPLE_SIZE, 3))
        self._paired = np.zeros((PAIRED_SAMPLE_SIZE, 6))  # reading, gravity's direction
        self._reading_states = np.full((READING_SAMPLE_SIZE, 0), math.nan)
        self._paired_states = np.full((PAIRED_SAMPLE_SIZE, 0), math.nan)
        self._paired_recorded = 0
        self._paired_draw = random.Random(1)
        self._recorded = 0  # readings offered: the draw's population
        self._draw = random.Random(0)  # deterministic: the same stream, the same draw

    def _allocate(self, capacity: int, k: int) -> None:
        self._capacity = capacity
        self._k = k
        self._points = np.zeros((capacity, 3))  # the samples that won their place: kNN geometry
        # readings merged into each point: count, sum and second moment about the anchor
        self._counts = np.zeros(capacity)
        self._sums = np.zeros((capacity, 3))
        self._moments = np.zeros((capacity, 6))  # upper triangle: xx xy xz yy yz zz
        self._up_sums = np.zeros((capacity, 3))  # gravity directions of the paired readings
        self._state_sums = np.full((capacity, self._state_size), math.nan)  # NaN: unknown
        self._nbr_dist = np.full((capacity, k), np.inf)  # distances to the k nearest others
        self._nbr_index = np.full((capacity, k), -1, dtype=np.intp)
        self._kth = np.full(capacity, np.inf)  # largest of those: a closer newcomer enters
        self._score = np.full(capacity, np.inf)  # mean k-NN distance
        self._fill = 0
        self._weakest = 0  # index of the lowest score: the next to be replaced
        self._weakest_score = math.inf

    # -- read-only state -----------------------------------------------------------------------

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def k(self) -> int:
        return self._k

    @property
    def fill(self) -> int:
        """How many samples the buffer holds (at most ``capacity``)."""
        return self._fill

    @property
    def seen(self) -> int:
        """Samples offered to ``add`` since construction or ``clear``."""
        return self._seen

    @property
    def reference(self) -> Calibration | None:
        """The calibration given to :meth:`set_reference` (screens and merges), if any."""
        return None if self._reference is None else self._reference.calibration

    @property
    def merging(self) -> bool:
        """Whether samples that are not unique merge (a reference that may merge is set)."""
        return self._merging

    @property
    def tolerance(self) -> float | None:
        """Largest relative magnitude error the reference accepts, if a reference is set."""
        return None if self._reference is None else self._reference.tolerance

    @property
    def reference_checks(self) -> tuple[int, int]:
        """(samples judged, magnitude outliers among them) since the reference was set: the
        owner tells from these when the reference no longer describes the sensor."""
        if self._reference is None:
            return 0, 0
        return self._reference.checked, self._reference.outliers

    @property
    def samples(self) -> np.ndarray:
        """The buffered points, (fill, 3), a copy in input units.

        Each is the sample that won its place, or once others were merged into it, their mean
        (see the module docstring); ``counts`` says how many readings each stands for.
        """
        n = self._fill
        counts = self._counts[:n]
        means = self._points[:n] + self._sums[:n] / np.maximum(counts, 1.0)[:, None]
        merged = np.flatnonzero(counts > 1.0)
        if self._projection is None or len(merged) == 0:
            return means
        screen = self._projection
        c = counts[merged]
        shift = self._sums[merged] / c[:, None]  # mean minus anchor
        second = self._moments[merged][:, _UPPER] / c[:, None, None]
        covariance = second - shift[:, :, None] * shift[:, None, :]
        means[merged] = screen.on_surface_mean(means[merged], covariance)
        return means

    @property
    def readings(self) -> np.ndarray:
        """A uniform random draw of recent screened readings (up to READING_SAMPLE_SIZE), a copy.

        Unlike ``samples`` (the most spread-out ones), these show where the readings really
        lie: on the field's sphere, or filling a still sensor's noise cloud whose rim the
        uniqueness rule keeps. ``coverage()`` checks the shell against them.
        """
        return self._readings[: min(self._recorded, READING_SAMPLE_SIZE)].copy()

    @property
    def paired_readings(self) -> tuple[np.ndarray, np.ndarray]:
        """(readings (m, 3), gravity's unit direction beside each (m, 3)): a uniform random draw
        of the recent screened readings that came paired with the accelerometer, copies."""
        rows = self._paired[: min(self._paired_recorded, PAIRED_SAMPLE_SIZE)]
        return rows[:, :3].copy(), rows[:, 3:].copy()

    @property
    def ups(self) -> np.ndarray:
        """Gravity's mean unit direction behind each buffered point, (fill, 3), NaN rows where
        no reading of it came paired with the accelerometer (see ``add``)."""
        sums = self._up_sums[: self._fill]
        norms = np.linalg.norm(sums, axis=1)
        with np.errstate(invalid='ignore', divide='ignore'):
            ups = sums / norms[:, None]
        ups[~(norms > 0)] = np.nan
        return ups

    @property
    def paired(self) -> int:
        """Buffered points with a gravity direction."""
        return int(np.count_nonzero(np.any(self._up_sums[: self._fill] != 0.0, axis=1)))

    @property
    def anchors(self) -> np.ndarray:
        """The samples that won their places, (fill, 3), a copy: what the uniqueness rule
        measures (``samples`` differ from them only by what was merged in)."""
        return self._points[: self._fill].copy()

    @property
    def counts(self) -> np.ndarray:
        """How many readings each buffered point stands for, (fill,): the weights to fit with."""
        return self._counts[: self._fill].copy()

    @property
    def scores(self) -> np.ndarray:
        """Each anchor's mean distance to its k nearest buffered anchors (a copy)."""
        return self._score[: self._fill].copy()

    @property
    def mean_knn_distance(self) -> float:
        """Mean over the buffer of each sample's mean k-NN distance, input units (0 below 2)."""
        if self._fill < 2:
            return 0.0
        return float(np.mean(self._score[: self._fill]))

    @property
    def relative_knn_distance(self) -> float:
        """``mean_knn_distance`` over the field radius in input units: scale-free (0 below 2).

        It still shrinks as N grows (N points share one sphere); ``coverage()`` does not.
        """
        radius = self.field_radius()
        if self._fill < 2 or not radius > 0.0:
            return 0.0
        return self.mean_knn_distance / radius

    def field_radius(self) -> float:
        """The field's radius in input units: from the reference, else a sphere fit of the buffer.

        Returns 0.0 when it cannot be told (fewer than two distinct samples).
        """
        reference = self.reference
        if reference is not None:
            return reference.field_radius()
        return _sphere_radius(self._points[: self._fill])

    def coverage(self) -> Coverage:
        """Share of equal-area direction cells occupied, after centring/whitening (N-free).

        The shell is checked against ``readings``: a still sensor's noise rim is no coverage.
        """
        return direction_coverage(self.samples, self.reference, self.readings)

    # -- feeding -------------------------------------------------------------------------------

    def add(self, sample: ArrayLike, up: Sequence[float] | None = None,
            state: Sequence[float] | None = None) -> str:
        """Offer one screened reading (3,); returns the outcome (see :data:`OUTCOMES`).
        ``up``: gravity's unit direction paired with it (the accelerometer), or None; a buffered
        point carries the mean direction of its readings (``ups``). ``state``: the reading's
        state (``forget_states``' size; None: unknown), for ``shift``.

        Raises ValueError for a malformed, non-finite or all-zero sample: screening is the
        caller's job (``screening``), done once per message.
        """
        x = np.asarray(sample, dtype=float)
        if x.size != 3:
            raise ValueError(f'a sample has 3 components, got shape {x.shape}')
        x = x.reshape(3)
        x0, x1, x2 = x.tolist()
        if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)) or not (
                x0 or x1 or x2):
            raise ValueError(f'a sample must be finite and not all zero, got {x.tolist()}; '
                             'screen readings before buffering them')
        if state is None:
            state = (math.nan,) * self._state_size
        elif len(state) != self._state_size:
            raise ValueError(f'a state has {self._state_size} values here, got {len(state)}')
        self._seen += 1
        if self._reference is not None and self._reference.check((x0, x1, x2)):
            return 'magnitude_outlier'
        self._record_reading(x, state)
        if up is not None:
            self._record_paired(x, up, state)
        return self._admit(x, up, state)

    def _record_reading(self, x: np.ndarray, state: Sequence[float]) -> None:
        """Reservoir sampling (Algorithm R) over a population capped at READING_HORIZON."""
        self._recorded += 1
        if self._recorded <= READING_SAMPLE_SIZE:
            slot = self._recorded - 1
        else:
            slot = int(self._draw.random() * min(self._recorded, READING_HORIZON))
            if slot >= READING_SAMPLE_SIZE:
                return
        self._readings[slot] = x
        self._reading_states[slot] = state

    def _record_paired(self, x: np.ndarray, up: Sequence[float], state: Sequence[float]
                       ) -> None:
        """The same draw over the paired readings, with gravity's direction."""
        self._paired_recorded += 1
        slot = self._paired_recorded - 1
        if slot >= PAIRED_SAMPLE_SIZE:
            slot = int(self._paired_draw.random() * min(self._paired_recorded, READING_HORIZON))
            if slot >= PAIRED_SAMPLE_SIZE:
                return
        self._paired[slot, :3] = x
        self._paired[slot, 3:] = up
        self._paired_states[slot] = state

    def _admit(self, x: np.ndarray, up: Sequence[float] | None = None,
               state: Sequence[float] = ()) -> str:
        """The uniqueness rule for a screened sample; a sample that is not unique is merged."""
        n = self._fill
        if n == 0:
            self._store(0, x, up, state)
            self._fill = 1
            self._refresh_all()
            return 'added'
        diff = self._points[:n] - x
        distances = np.sqrt(np.einsum('ij,ij->i', diff, diff))
        nearest = int(distances.argmin())
        if distances[nearest] == 0.0 and np.array_equal(self._points[nearest], x):
            return 'duplicate'
        if n < self._capacity:
            self._place(n, x, distances, up, state)
            return 'added'
        k = self._k
        own_score = float(np.partition(distances, k - 1)[:k].mean())
        # Strictly higher: a candidate only as unique as the weakest sample changes nothing.
        if own_score > self._weakest_score:
            self._place(self._weakest, x, distances, up, state)
            return 'replaced'
        if self._merging:
            self._merge(nearest, x, up, state)
            self.merged += 1
        return 'not_unique'

    def _merge(self, slot: int, x: np.ndarray, up: Sequence[float] | None = None,
               state: Sequence[float] = ()) -> None:
        """Add reading ``x`` to ``slot``'s count, sum and second moment (about the anchor, so
        a large hard-iron offset costs no precision). Plain floats: this runs per sample."""
        a0, a1, a2 = self._points[slot].tolist()
        x0, x1, x2 = x.tolist()
        d0, d1, d2 = x0 - a0, x1 - a1, x2 - a2
        self._counts[slot] += 1.0
        self._sums[slot] += (d0, d1, d2)
        self._moments[slot] += (d0 * d0, d0 * d1, d0 * d2, d1 * d1, d1 * d2, d2 * d2)
        if up is not None:
            self._up_sums[slot] += up
        if self._state_size:
            self._state_sums[slot] += state

    def add_many(self, samples: ArrayLike) -> dict[str, int]:
        """Offer many samples (n, 3) in order; returns how often each outcome happened."""
        rows = np.asarray(samples, dtype=float)
        if rows.size == 0:
            return dict.fromkeys(OUTCOMES, 0)
        if rows.ndim != 2 or rows.shape[1] != 3:
            raise ValueError(f'samples must have shape (n, 3), got {rows.shape}')
        counts = dict.fromkeys(OUTCOMES, 0)
        for row in rows:
            counts[self.add(row)] += 1
        return counts

    # -- reference, size, reset ----------------------------------------------------------------

    def set_reference(
        self,
        calibration: Calibration | None,
        tolerance: float = DEFAULT_MAGNITUDE_TOLERANCE,
        merge: bool = False,
    ) -> int:
        """Screen by ``calibration`` (None: stop); returns how many points it evicted.

        A sample whose corrected magnitude is off ``F`` by more than ``tolerance`` (relative) is
        refused, and buffered points it shows to be outliers are evicted at once, so a spike that
        got in before any reference existed does not survive. When most of the buffer disagrees
        with the reference nothing is evicted: the two describe different situations and the
        owner decides (``reference_checks``). ``merge``: samples that are not unique merge into
        their nearest point, placed on this reference's surface -- only for a reference that
        describes every direction (a full fit of the buffer), or the means would bend.
        """
        if calibration is None:
            self._reference = None
            self._merging = False
            return 0
        if not (math.isfinite(tolerance) and tolerance > 0.0):
            raise ValueError(f'tolerance must be a positive finite number, got {tolerance}')
        screen = _MagnitudeScreen(calibration, float(tolerance))
        self._reference = screen
        self._merging = bool(merge)
        if merge:
            self._projection = screen
        return self._evict_outliers(screen)

    def _evict_outliers(self, screen: _MagnitudeScreen) -> int:
        """Remove the buffered points ``screen`` refuses, unless most of the buffer would go."""
        if self._fill == 0:
            return 0
        relative = screen.relative(self.samples)
        keep = np.abs(relative - 1.0) <= screen.tolerance
        removed = int(self._fill - np.count_nonzero(keep))
        if removed == 0 or 2 * removed > self._fill:
            return 0
        self._keep_rows(keep)
        self.evicted += removed
        return removed

    def _keep_rows(self, keep: np.ndarray) -> None:
        """Compact the buffer to the rows where ``keep`` is True, then rebuild the neighbours."""
        n = self._fill
        for array in self._per_point():
            kept = array[:n][keep]
            array[: len(kept)] = kept
        self._fill = int(np.count_nonzero(keep))
        self._refresh_all()

    def resize(self, capacity: int | None = None, k: int | None = None) -> None:
        """Change capacity and/or k at run time, keeping the most unique samples that fit.

        Shrinking removes the weakest sample one at a time (the replacement rule run backwards),
        so what stays is what the rule would have kept.
        """
        capacity, k = _checked_size(
            self._capacity if capacity is None else capacity, self._k if k is None else k
        )
        self._reallocate(max(capacity, self._fill), k)
        while self._fill > capacity:
            self._remove(self._weakest)
        if self._capacity != capacity:
            self._reallocate(capacity, k)

    def _per_point(self) -> tuple[np.ndarray, ...]:
        """Every per-point array but the neighbour lists (those are rebuilt)."""
        return (self._points, self._counts, self._sums, self._moments, self._up_sums,
                self._state_sums)

    # -- states --------------------------------------------------------------------------------

    def forget_states(self, size: int) -> None:
        """States from now on have ``size`` values; those held are unknown (the owner's record
        changed its meaning), so ``shift`` removes their points."""
        self._state_size = int(size)
        self._state_sums = np.full((self._capacity, self._state_size), math.nan)
        self._reading_states = np.full((READING_SAMPLE_SIZE, self._state_size), math.nan)
        self._paired_states = np.full((PAIRED_SAMPLE_SIZE, self._state_size), math.nan)

    def shift(self, change: Callable[[np.ndarray], np.ndarray]) -> int:
        """Move every point and recent reading by ``change(states)`` ((n, size) states, a
        point's the mean of its readings', to (n, 3) shifts): what was taken off them changed.
        A point's readings move together by their mean's shift (exact for the mean, its spread
        kept). What cannot move (an unknown state, or a NaN shift) is forgotten; returns how
        many points were. The neighbour lists are rebuilt; the reference is the owner's to
        set."""
        n = self._fill
        moves, movable = moves_of(change, self._state_sums[:n] / self._counts[:n, None])
        self._points[:n][movable] += moves[movable]
        removed = int(n - np.count_nonzero(movable))
        if removed:
            self._keep_rows(movable)
        else:
            self._refresh_all()
        kept = _shift_draw(self._readings, self._reading_states,
                           min(self._recorded, READING_SAMPLE_SIZE), change)
        if kept is not None:  # the draw starts again from what it kept
            self._recorded = kept
        kept = _shift_draw(self._paired, self._paired_states,
                           min(self._paired_recorded, PAIRED_SAMPLE_SIZE), change)
        if kept is not None:
            self._paired_recorded = kept
        return removed

    def _reallocate(self, capacity: int, k: int) -> None:
        n = self._fill
        saved = [array[:n].copy() for array in self._per_point()]
        self._allocate(capacity, k)
        self._fill = n
        for array, values in zip(self._per_point(), saved, strict=True):
            array[:n] = values
        self._refresh_all()

    def clear(self) -> None:
        """Forget every sample, reading and the reference; keeps capacity and k."""
        self._fill = 0
        self._counts.fill(0.0)
        self._reference = self._projection = None
        self._merging = False
        self._nbr_dist.fill(np.inf)
        self._nbr_index.fill(-1)
        self._kth.fill(np.inf)
        self._score.fill(np.inf)
        self._weakest, self._weakest_score = 0, math.inf
        self._seen = 0
        self._recorded = 0
        self._draw = random.Random(0)
        self._paired_recorded = 0
        self._paired_draw = random.Random(1)
        self.evicted = 0
        self.merged = 0

    # -- neighbour bookkeeping -----------------------------------------------------------------

    def _place(self, slot: int, x: np.ndarray, distances: np.ndarray,
               up: Sequence[float] | None = None, state: Sequence[float] = ()) -> None:
        """Store ``x`` in ``slot`` (append or replace); ``distances``: x to the old rows."""
        n_before = self._fill
        n_after = max(n_before, slot + 1)
        if n_after - 1 <= self._k:  # still filling the first k + 1: every row changes
            self._store(slot, x, up, state)
            self._fill = n_after
            self._refresh_all()
            return
        rows_before = slice(0, n_before)
        enters = distances < self._kth[rows_before]  # the newcomer is nearer than their k-th
        if slot < n_before:
            # Rows that lose the replaced sample as a neighbour need a fresh search.
            lost = (self._nbr_index[rows_before] == slot).any(axis=1)
            lost[slot] = True
            enters &= ~lost
            rebuild = np.flatnonzero(lost)
        else:
            rebuild = np.array([slot])
        if slot < n_before and self._merging:
            self._fold_displaced(slot)
        self._store(slot, x, up, state)
        self._fill = n_after
        gain = np.flatnonzero(enters)
        if len(gain):  # the newcomer takes the place of their farthest neighbour: O(k) each
            farthest = self._nbr_dist[gain].argmax(axis=1)
            self._nbr_dist[gain, farthest] = distances[gain]
            self._nbr_index[gain, farthest] = slot
            nearest = self._nbr_dist[gain]
            self._kth[gain] = nearest.max(axis=1)
            self._score[gain] = nearest.mean(axis=1)
        self._refresh_rows(rebuild)

    def _store(self, slot: int, x: np.ndarray, up: Sequence[float] | None = None,
               state: Sequence[float] = ()) -> None:
        self._points[slot] = x
        self._counts[slot] = 1.0
        self._sums[slot] = 0.0
        self._moments[slot] = 0.0
        self._up_sums[slot] = 0.0 if up is None else up
        self._state_sums[slot] = state

    def _fold_displaced(self, slot: int) -> None:
        """The replaced point's readings join its nearest neighbour: nothing measured is lost.

        Its sum and second moment move to the neighbour's anchor exactly (a shift of origin).
        """
        row = self._nbr_dist[slot]
        target = int(self._nbr_index[slot, int(row.argmin())])
        if not (0 <= target < self._fill and target != slot):
            return
        count, sums = float(self._counts[slot]), self._sums[slot]
        shift = self._points[slot] - self._points[target]  # old anchor seen from the new one
        outer = np.outer(sums, shift)
        moments = (
            self._moments[slot][_UPPER] + outer + outer.T + count * np.outer(shift, shift)
        )
        self._counts[target] += count
        self._sums[target] += sums + count * shift
        self._moments[target] += moments[_TRIU]
        self._up_sums[target] += self._up_sums[slot]
        self._state_sums[target] += self._state_sums[slot]

    def _remove(self, slot: int) -> None:
        """Remove the sample in ``slot``; the last sample moves into it."""
        n = self._fill
        last = n - 1
        touched = (self._nbr_index[:n] == slot).any(axis=1)
        if slot != last:
            for array in self._per_point():
                array[slot] = array[last]
            self._nbr_dist[slot] = self._nbr_dist[last]
            self._nbr_index[slot] = self._nbr_index[last]
            self._kth[slot] = self._kth[last]
            self._score[slot] = self._score[last]
            touched[slot] = touched[last]
            self._nbr_index[:n][self._nbr_index[:n] == last] = slot
        self._fill = last
        self._score[last] = np.inf
        self._counts[last] = 0.0
        if self._fill - 1 <= self._k:
            self._refresh_all()
        else:
            self._refresh_rows(np.flatnonzero(touched[: self._fill]))

    def _refresh_all(self) -> None:
        self._nbr_dist.fill(np.inf)
        self._nbr_index.fill(-1)
        self._kth.fill(np.inf)
        self._score.fill(np.inf)
        self._refresh_rows(np.arange(self._fill))

    def _refresh_rows(self, rows: np.ndarray) -> None:
        """Recompute the neighbour lists and scores of ``rows`` from scratch, then the weakest."""
        n = self._fill
        neighbours = min(self._k, n - 1)
        points = self._points[:n]
        if neighbours > 0:
            for start in range(0, len(rows), _CHUNK_ROWS):
                block = rows[start:start + _CHUNK_ROWS]
                diff = points[block, None, :] - points[None, :, :]
                distances = np.sqrt(np.einsum('ijk,ijk->ij', diff, diff))
                distances[np.arange(len(block)), block] = np.inf  # never your own neighbour
                index = np.argpartition(distances, neighbours - 1, axis=1)[:, :neighbours]
                nearest = np.take_along_axis(distances, index, axis=1)
                self._nbr_index[block, :neighbours] = index
                self._nbr_dist[block, :neighbours] = nearest
                # Fewer than k others exist while filling: any newcomer enters the list.
                self._kth[block] = nearest.max(axis=1) if neighbours == self._k else np.inf
                self._score[block] = nearest.mean(axis=1)
        if n:
            self._weakest = int(self._score[:n].argmin())
            self._weakest_score = float(self._score[self._weakest])
        else:
            self._weakest, self._weakest_score = 0, math.inf


def moves_of(change: Callable[[np.ndarray], np.ndarray], states: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """(``change(states)``, which rows can move: a known state and a finite shift)."""
    moves = np.asarray(change(states), dtype=float)
    return moves, np.all(np.isfinite(moves), axis=1) & np.all(np.isfinite(states), axis=1)


def _shift_draw(table: np.ndarray, states: np.ndarray, count: int,
                change: Callable[[np.ndarray], np.ndarray]) -> int | None:
    """Shift the first ``count`` rows of a draw (the reading in ``table``'s first three columns)
    by ``change(states)``; rows that cannot move are dropped and the rest moved up. Returns
    the rows kept when any were dropped, else None."""
    if count == 0:
        return None
    moves, movable = moves_of(change, states[:count])
    table[:count, :3][movable] += moves[movable]
    if movable.all():
        return None
    kept = int(np.count_nonzero(movable))
    table[:kept] = table[:count][movable]
    states[:kept] = states[:count][movable]
    return kept


class _MagnitudeScreen:
    """Refuses readings whose corrected magnitude is off a reference by more than ``tolerance``
    (relative), counting how many it judged and refused."""

    def __init__(self, calibration: Calibration, tolerance: float) -> None:
        self.calibration = calibration
        self.matrix = calibration.matrix / calibration.field_strength  # unit radius
        self.inverse = np.linalg.inv(self.matrix)
        self.offset = calibration.offset.copy()
        self._matrix = self.matrix.tolist()
        self._offset = self.offset.tolist()
        self.tolerance = tolerance
        self.checked = 0
        self.outliers = 0

    def whiten(self, x: Sequence[float]) -> list[float]:
        """``M (x - b) / F`` in plain floats (on 3-vectors numpy's per-call overhead dominates)."""
        d = [a - b for a, b in zip(x, self._offset, strict=True)]
        return [r[0] * d[0] + r[1] * d[1] + r[2] * d[2] for r in self._matrix]

    def on_surface_mean(self, means: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """Where the readings averaged into each row lie on average *along the surface*.

        A plain mean of readings spread over a patch of a curved surface sinks inside it by
        about the tangential variance over twice the radius. In whitened space (unit sphere)
        the mean radius is, to second order, ``|ū| + tr(P C) / (2 |ū|)`` with ``C`` the
        readings' covariance and ``P`` the projection across the radius; the point returned has
        the mean's direction and that radius. Third-order terms are below 1e-4 of the radius
        for the patches of a 100-point buffer (measured: 1e-4 where plain means sink by 2.5 %).
        """
        u = (means - self.offset) @ self.matrix.T
        radius = np.linalg.norm(u, axis=1)
        safe = np.maximum(radius, 1e-300)
        direction = u / safe[:, None]
        whitened = self.matrix @ covariance @ self.matrix.T
        trace = np.trace(whitened, axis1=1, axis2=2)
        radial = np.einsum('ni,nij,nj->n', direction, whitened, direction)
        surface = radius + (trace - radial) / (2.0 * safe)
        return self.offset + (direction * surface[:, None]) @ self.inverse.T

    def relative(self, points: np.ndarray) -> np.ndarray:
        """|corrected| / F for each row of ``points``."""
        return np.linalg.norm((points - self.offset) @ self.matrix.T, axis=1)

    def check(self, x: Sequence[float]) -> bool:
        """True when ``x`` is a magnitude outlier (counted)."""
        outlier = not abs(math.hypot(*self.whiten(x)) - 1.0) <= self.tolerance
        self.checked += 1
        self.outliers += outlier
        return outlier


def _checked_size(capacity: int, k: int) -> tuple[int, int]:
    if isinstance(capacity, bool) or int(capacity) != capacity or capacity < 2:
        raise ValueError(f'capacity must be an integer >= 2, got {capacity!r}')
    if isinstance(k, bool) or int(k) != k or not 1 <= k < capacity:
        raise ValueError(f'k must be an integer in [1, capacity - 1], got {k!r}')
    return int(capacity), int(k)


def _sphere_radius(points: np.ndarray) -> float:
    """Radius of the least-squares sphere through ``points`` (centred and scaled first).

    Falls back to the RMS distance from the centroid when the points do not determine a sphere
    (a single ring, say), which is then the ring's radius: the right scale either way.
    """
    if len(points) < 2:
        return 0.0
    centroid = points.mean(axis=0)
    centred = points - centroid
    spread = float(np.sqrt(np.mean(np.einsum('ij,ij->i', centred, centred))))
    if not spread > 0.0:
        return 0.0
    unit = centred / spread
    if len(points) >= 4:
        design = np.column_stack([2.0 * unit, np.ones(len(unit))])
        target = np.einsum('ij,ij->i', unit, unit)
        solution, _, rank, singular = np.linalg.lstsq(design, target, rcond=None)
        if rank == 4 and singular[-1] > 1e-3 * singular[0]:
            squared = solution[3] + float(solution[:3] @ solution[:3])
            if squared > 0.0 and math.isfinite(squared):
                return spread * math.sqrt(squared)
    return spread
