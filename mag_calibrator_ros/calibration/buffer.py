"""A fixed-size buffer of well-spread magnetometer samples: the brief's kNN uniqueness rule, fixed.

The brief's library (mag-calibrator-rs) keeps N samples and, once full, lets a new sample replace
the buffered sample with the lowest mean distance to its k nearest neighbours when the new
sample's own mean k-NN distance is higher. Its measured flaws, and what this module does instead:

- inconsistent scoring (buffered rows counted their zero self-distance, so every candidate won):
  every score here is the mean distance to k *other* points, the candidate's against the buffer;
- a manual pre-scaler and absolute thresholds: there are none, every decision compares distances
  with distances, so input in T, µT, gauss or counts gives the same decisions;
- an O(N² log N) recomputation per sample: each buffered point keeps its k nearest distances and
  indices; a sample that is not unique costs one O(N) distance pass, a replacement recomputes only
  the rows it touches (on average about 2k of them);
- duplicates, zero components and spikes: exact duplicates and all-zero vectors are refused (one
  zero component is a legitimate reading and kept), and once a reference calibration exists,
  gross magnitude outliers are refused and evicted. Spikes are the most "unique" samples of all,
  so without this they would be the last to leave.

Memory is fixed: every array is allocated once for the configured capacity.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.calibration import Calibration
from mag_calibrator_ros.calibration.coverage import Coverage, direction_coverage

REJECT_REASONS = ('non_finite', 'zero', 'saturated', 'duplicate', 'magnitude_outlier')
"""Why :meth:`SampleBuffer.add` refused a sample (each one counted in ``rejects``)."""

OUTCOMES = ('added', 'replaced', 'not_unique', *REJECT_REASONS)
"""Everything :meth:`SampleBuffer.add` can return."""

DEFAULT_CAPACITY = 100
"""About ten samples per parameter of the full model (offset 3 + symmetric matrix 6), small enough
that a sample costs microseconds and a fit milliseconds."""

DEFAULT_K = 6
"""The six nearest neighbours are the first ring around a point on an evenly covered sphere, so
the score measures local crowding rather than the distance to one twin. Measured (12 'strong'
synthetic tumbles of benchmarks/scenarios.py, N = 100, a plain algebraic full fit of the buffer):
mean direction error 0.213 / 0.210 / 0.197 / 0.215 deg for k = 2 / 4 / 6 / 8 (random 100-sample
subsets: 0.218 deg). The differences are small; k = 6 was best and costs little (the replacement
work grows with k)."""

DEFAULT_MAGNITUDE_TOLERANCE = 0.3
"""A sample whose corrected magnitude is off the reference field by more than 30 % is a gross
outlier (a spike or a magnet nearby). Good data under a calibration that passed the fit gates stays
within a few per cent, so this never rejects it."""

STALE_REFERENCE_SHARE = 0.5
"""If more than half of a window of samples are magnitude outliers, the reference no longer
describes the sensor (moved, re-mounted, a stale file): it is dropped rather than starving the
buffer of the data a new calibration needs."""

_CHUNK_ROWS = 64  # rows per block when recomputing many neighbour lists: bounded temporaries


class SampleBuffer:
    """Keeps the ``capacity`` most spread-out samples seen so far, screening bad input.

    ``add`` returns what happened: 'added' (buffer not yet full), 'replaced', 'not_unique', or a
    reason from :data:`REJECT_REASONS`.
    """

    def __init__(
        self,
        capacity: int = DEFAULT_CAPACITY,
        k: int = DEFAULT_K,
        full_scale: float | None = None,
        magnitude_tolerance: float = DEFAULT_MAGNITUDE_TOLERANCE,
    ) -> None:
        capacity, k = _checked_size(capacity, k)
        if full_scale is not None and not (math.isfinite(full_scale) and full_scale > 0.0):
            raise ValueError(
                f'full_scale must be a positive finite number or None, got {full_scale}'
            )
        if not (math.isfinite(magnitude_tolerance) and magnitude_tolerance > 0.0):
            raise ValueError(
                f'magnitude_tolerance must be a positive finite number, got {magnitude_tolerance}'
            )
        self.full_scale = None if full_scale is None else float(full_scale)
        self.magnitude_tolerance = float(magnitude_tolerance)
        self._allocate(capacity, k)
        self._seen = 0
        self._rejects = dict.fromkeys(REJECT_REASONS, 0)
        self.evicted = 0
        """Buffered samples removed because a new reference showed them to be outliers."""
        self.reference_drops = 0
        """How often a reference was dropped as stale (see :data:`STALE_REFERENCE_SHARE`)."""
        self._reference: Calibration | None = None
        self._ref_matrix = np.eye(3)
        self._ref_offset = np.zeros(3)
        self._window_checked = 0
        self._window_outliers = 0

    def _allocate(self, capacity: int, k: int) -> None:
        self._capacity = capacity
        self._k = k
        self._points = np.zeros((capacity, 3))
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
    def rejects(self) -> dict[str, int]:
        """Refused samples per reason (a copy; keys are :data:`REJECT_REASONS`)."""
        return dict(self._rejects)

    @property
    def reference(self) -> Calibration | None:
        """The calibration used to spot magnitude outliers, if any."""
        return self._reference

    @property
    def samples(self) -> np.ndarray:
        """The buffered samples, (fill, 3), a copy in input units."""
        return self._points[: self._fill].copy()

    @property
    def scores(self) -> np.ndarray:
        """Each buffered sample's mean distance to its k nearest buffered neighbours (a copy)."""
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
        if self._reference is not None:
            # |M (x - b)| = F on the ellipsoid; its mean radius in raw units is F / det(M)^(1/3).
            det = float(np.linalg.det(self._reference.matrix))
            return self._reference.field_strength / det ** (1.0 / 3.0)
        return _sphere_radius(self._points[: self._fill])

    def coverage(self) -> Coverage:
        """Share of equal-area direction cells occupied, after centring/whitening (N-free)."""
        return direction_coverage(self.samples, self._reference)

    # -- feeding -------------------------------------------------------------------------------

    def add(self, sample: ArrayLike) -> str:
        """Offer one sample (3,); returns the outcome (see :data:`OUTCOMES`)."""
        x = np.asarray(sample, dtype=float)
        if x.size != 3:
            raise ValueError(f'a sample has 3 components, got shape {x.shape}')
        x = x.reshape(3)
        self._seen += 1
        reason = self._screen(x)
        if reason is not None:
            self._rejects[reason] += 1
            return reason
        n = self._fill
        if n == 0:
            self._points[0] = x
            self._fill = 1
            self._refresh_all()
            return 'added'
        diff = self._points[:n] - x
        distances = np.sqrt(np.einsum('ij,ij->i', diff, diff))
        nearest = int(distances.argmin())
        if distances[nearest] == 0.0 and np.array_equal(self._points[nearest], x):
            self._rejects['duplicate'] += 1
            return 'duplicate'
        if n < self._capacity:
            self._place(n, x, distances)
            return 'added'
        k = self._k
        own_score = float(np.partition(distances, k - 1)[:k].mean())
        # Strictly higher: a candidate only as unique as the weakest sample changes nothing.
        if own_score > self._weakest_score:
            self._place(self._weakest, x, distances)
            return 'replaced'
        return 'not_unique'

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

    def _screen(self, x: np.ndarray) -> str | None:
        """The first reject reason that applies to ``x``, or None. Plain floats: 3 values only."""
        x0, x1, x2 = x.tolist()
        if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
            return 'non_finite'
        if x0 == 0.0 and x1 == 0.0 and x2 == 0.0:
            return 'zero'
        if self.full_scale is not None and max(abs(x0), abs(x1), abs(x2)) >= self.full_scale:
            return 'saturated'
        if self._reference is not None and self._check_magnitude(x):
            return 'magnitude_outlier'
        return None

    def _check_magnitude(self, x: np.ndarray) -> bool:
        """True for a gross magnitude outlier; drops the reference once it is clearly stale."""
        relative = float(np.linalg.norm(self._ref_matrix @ (x - self._ref_offset)))
        outlier = not abs(relative - 1.0) <= self.magnitude_tolerance
        self._window_checked += 1
        self._window_outliers += outlier
        if self._window_checked >= max(100, self._capacity):
            if self._window_outliers > STALE_REFERENCE_SHARE * self._window_checked:
                self.reference_drops += 1
                self._reference = None
                self._window_checked = self._window_outliers = 0
                return False
            self._window_checked = self._window_outliers = 0
        return outlier

    # -- reference, size, reset ----------------------------------------------------------------

    def set_reference(self, calibration: Calibration | None) -> int:
        """Use ``calibration`` to refuse gross magnitude outliers (None: stop doing so).

        Buffered samples that the new reference shows to be outliers are evicted at once, so a
        spike that got in before any calibration existed does not survive; returns how many.
        When most of the buffer disagrees with the reference, nothing is evicted: the buffer
        and the reference describe different situations, and new samples decide (see
        :data:`STALE_REFERENCE_SHARE`). A reference that moved little (online tracking) keeps
        the outlier statistics gathered under the previous one.
        """
        previous = self._reference
        self._reference = calibration
        if _moved(previous, calibration, 0.5 * self.magnitude_tolerance):
            self._window_checked = self._window_outliers = 0
        if calibration is None:
            return 0
        self._ref_matrix = calibration.matrix / calibration.field_strength
        self._ref_offset = calibration.offset.copy()
        if self._fill == 0:
            return 0
        relative = np.linalg.norm(
            (self._points[: self._fill] - self._ref_offset) @ self._ref_matrix.T, axis=1
        )
        keep = np.abs(relative - 1.0) <= self.magnitude_tolerance
        removed = int(self._fill - np.count_nonzero(keep))
        if removed == 0 or removed > STALE_REFERENCE_SHARE * self._fill:
            return 0
        kept = self._points[: self._fill][keep]
        self._fill = len(kept)
        self._points[: self._fill] = kept
        self._refresh_all()
        self.evicted += removed
        return removed

    def resize(self, capacity: int | None = None, k: int | None = None) -> None:
        """Change capacity and/or k at run time, keeping the most unique samples that fit.

        Shrinking removes the weakest sample one at a time (the replacement rule run backwards),
        so what stays is what the rule would have kept.
        """
        capacity, k = _checked_size(
            self._capacity if capacity is None else capacity, self._k if k is None else k
        )
        points = self._points[: self._fill].copy()
        self._allocate(max(capacity, len(points)), k)
        self._fill = len(points)
        self._points[: self._fill] = points
        self._refresh_all()
        while self._fill > capacity:
            self._remove(self._weakest)
        if self._capacity != capacity:
            points = self._points[: self._fill].copy()
            self._allocate(capacity, k)
            self._fill = len(points)
            self._points[: self._fill] = points
            self._refresh_all()

    def clear(self) -> None:
        """Forget every sample and counter; keeps capacity, k, full scale and the reference."""
        self._fill = 0
        self._nbr_dist.fill(np.inf)
        self._nbr_index.fill(-1)
        self._kth.fill(np.inf)
        self._score.fill(np.inf)
        self._weakest, self._weakest_score = 0, math.inf
        self._seen = 0
        self._rejects = dict.fromkeys(REJECT_REASONS, 0)
        self.evicted = 0
        self._window_checked = self._window_outliers = 0

    # -- neighbour bookkeeping -----------------------------------------------------------------

    def _place(self, slot: int, x: np.ndarray, distances: np.ndarray) -> None:
        """Store ``x`` in ``slot`` (append or replace); ``distances``: x to the old rows."""
        n_before = self._fill
        n_after = max(n_before, slot + 1)
        if n_after - 1 <= self._k:  # still filling the first k + 1: every row changes
            self._points[slot] = x
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
        self._points[slot] = x
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

    def _remove(self, slot: int) -> None:
        """Remove the sample in ``slot``; the last sample moves into it."""
        n = self._fill
        last = n - 1
        touched = (self._nbr_index[:n] == slot).any(axis=1)
        if slot != last:
            self._points[slot] = self._points[last]
            self._nbr_dist[slot] = self._nbr_dist[last]
            self._nbr_index[slot] = self._nbr_index[last]
            self._kth[slot] = self._kth[last]
            self._score[slot] = self._score[last]
            touched[slot] = touched[last]
            self._nbr_index[:n][self._nbr_index[:n] == last] = slot
        self._fill = last
        self._score[last] = np.inf
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


def _checked_size(capacity: int, k: int) -> tuple[int, int]:
    if isinstance(capacity, bool) or int(capacity) != capacity or capacity < 2:
        raise ValueError(f'capacity must be an integer >= 2, got {capacity!r}')
    if isinstance(k, bool) or int(k) != k or not 1 <= k < capacity:
        raise ValueError(f'k must be an integer in [1, capacity - 1], got {k!r}')
    return int(capacity), int(k)


def _moved(old: Calibration | None, new: Calibration | None, tolerance: float) -> bool:
    """Whether ``new`` judges magnitudes visibly differently from ``old`` (relative units)."""
    if old is None or new is None:
        return old is not new
    radius = old.field_strength / float(np.linalg.det(old.matrix)) ** (1.0 / 3.0)
    offset_shift = float(np.linalg.norm(new.offset - old.offset)) / radius
    matrix_shift = float(np.linalg.norm(
        new.matrix / new.field_strength - old.matrix / old.field_strength, ord=2
    )) * radius
    return not offset_shift + matrix_shift <= tolerance


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
