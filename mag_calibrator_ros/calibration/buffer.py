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

Two additions of ours, so that a buffer of N points calibrates about as well as a fit of every
sample. Measured on the 12 synthetic scenarios of benchmarks/bench_engine.py (`full` fitted to a
buffer of N = 100 fed 3,000 samples, weighted by ``counts``; direction error RMS, worst / mean):
the brief's rule alone 96° / 17° (spikes take over the buffer; 0.32° worst without spikes), with
the self-reference 0.43° / 0.26°, with merging as well 0.052° / 0.038° (fitting every sample:
0.044° / 0.034°). Merging with plain means instead of means placed on the surface: 0.50° / 0.20°,
worse than not merging; without passing a replaced point's readings on: 0.074° / 0.050°.

- self-reference: a reference calibration used to arrive only from outside (after a successful
  calibration), so a spiky stream filled the buffer with spikes (73 of 100 at 3 % spikes) and no
  fit ever succeeded to provide one. Now, once the buffer is full, it fits itself every
  ``capacity`` samples (fewer once it settles; amortised about 10 µs per sample at N = 100-1000)
  and a sane fit becomes the *provisional* reference: samples off its surface by more than
  ``outlier_threshold`` sigmas (one reading's noise and the fit's own uncertainty) are refused,
  buffered ones evicted;
- merging: 100 samples of 0.5 µT noise on 50 µT cannot locate an ellipsoid to better than about
  0.2° (Cramér-Rao), however well spread. Once a provisional reference exists, a sample that is
  not unique adds its information to its nearest buffered point instead of being dropped: each
  point keeps the count, sum and second moment of the readings it stands for (``counts``; fit
  with them as weights), and a replaced point's readings join its nearest neighbour. A plain
  mean of readings spread over a patch of a curved surface lies inside it (by d²/2R over a patch
  of size d) and, with unequal counts, would distort the shape; so ``samples`` places each mean
  back on the surface along its direction, using the readings' spread and the latest provisional
  reference (second order, see ``_MagnitudeScreen.on_surface_mean``). Placing them at read time
  rather than when merging means an early, rougher reference bends nothing for good. The
  buffered point keeps its original position (its *anchor*) for the uniqueness rule, which is
  unchanged.

Memory is fixed: every array is allocated once for the configured capacity.
"""

from __future__ import annotations

from collections.abc import Sequence
import math
import random

import numpy as np
from numpy.typing import ArrayLike

from mag_calibrator_ros.calibration.calibration import Calibration
from mag_calibrator_ros.calibration.coverage import Coverage, direction_coverage
from mag_calibrator_ros.calibration.ellipsoid import robust_sigma
from mag_calibrator_ros.calibration.fitting import FitOptions, FitResult, fit_calibration

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

SELF_REFERENCE_OPTIONS = FitOptions(model='full')
"""How the buffer fits itself for its provisional reference: the default gates, model ``full``,
the one that describes any magnetometer in a uniform field. A sphere or planar fit chosen because
``full`` was not yet determined judged unseen directions by up to 20 % and 110 % wrong (measured
on an early hand-tumble buffer), refusing good readings and bending merged means."""

MAX_SELF_FIT_PERIOD = 8
"""Once successive self-fits agree to within one reading's noise, the period between them
doubles up to 8 x capacity samples: the reference has settled, refitting mostly costs time."""

STALE_REFERENCE_SHARE = 0.5
"""If more than half of a window of samples are magnitude outliers, the reference no longer
describes the sensor (moved, re-mounted, a stale file): it is dropped rather than starving the
buffer of the data a new calibration needs."""

READING_SAMPLE_SIZE = 256
"""Readings kept as a random draw of the recent stream (``readings``): the evidence that the
buffer's shell is the field sphere and not the rim of a still sensor's noise (see
coverage.shell_directions). 256 tell a share of one half to within about 3 %."""

READING_HORIZON = 2048
"""The draw favours the last ~2,048 readings (each survives a geometric time of that mean), so
after a change (a re-mounted sensor, a moved magnet) it soon describes the new situation."""

_UPPER = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])  # 3x3 from the stored upper triangle
_TRIU = np.triu_indices(3)
_CHUNK_ROWS = 64  # rows per block when recomputing many neighbour lists: bounded temporaries


def reading_problem(x0: float, x1: float, x2: float, full_scale: float | None) -> str | None:
    """Why one reading can never be a sample ('non_finite', 'zero', 'saturated'), or None.

    All-zero is refused but one exact-zero component is a legitimate reading. Plain floats, as
    this runs for every message.
    """
    if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
        return 'non_finite'
    if x0 == 0.0 and x1 == 0.0 and x2 == 0.0:
        return 'zero'
    if full_scale is not None and max(abs(x0), abs(x1), abs(x2)) >= full_scale:
        return 'saturated'
    return None


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
        self_reference: bool = True,
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
        self.self_reference = bool(self_reference)
        """Fit the buffer now and then for a provisional reference, and merge (see above)."""
        self._allocate(capacity, k)
        self._seen = 0
        self._rejects = dict.fromkeys(REJECT_REASONS, 0)
        self.evicted = 0
        """Buffered samples removed because a new reference showed them to be outliers."""
        self.reference_drops = 0
        """How often a reference was dropped as stale (see :data:`STALE_REFERENCE_SHARE`)."""
        self.merged = 0
        """Samples that were not unique and were folded into their nearest buffered point."""
        self.self_fits = 0
        """Fits the buffer made of itself for a provisional reference (sane or not)."""
        self._external: _MagnitudeScreen | None = None  # set_reference()
        self._provisional: _MagnitudeScreen | None = None  # the buffer's own fit
        self._projection: _MagnitudeScreen | None = None  # its latest, kept to place the means
        self._since_self_fit = 0
        self._self_fit_period = capacity
        self._readings = np.zeros((READING_SAMPLE_SIZE, 3))
        self._screened = 0  # readings that passed the screen: the draw's population
        self._draw = random.Random(0)  # deterministic: the same stream, the same draw

    def _allocate(self, capacity: int, k: int) -> None:
        self._capacity = capacity
        self._k = k
        self._points = np.zeros((capacity, 3))  # the samples that won their place: kNN geometry
        # readings merged into each point: count, sum and second moment about the anchor
        self._counts = np.zeros(capacity)
        self._sums = np.zeros((capacity, 3))
        self._moments = np.zeros((capacity, 6))  # upper triangle: xx xy xz yy yz zz
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
        """The calibration given to :meth:`set_reference`, if any (and not dropped as stale)."""
        return None if self._external is None else self._external.calibration

    @property
    def provisional_reference(self) -> Calibration | None:
        """The buffer's own latest sane fit, used to refuse outliers and to merge, if any."""
        return None if self._provisional is None else self._provisional.calibration

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
        return self._readings[: min(self._screened, READING_SAMPLE_SIZE)].copy()

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
        reference = self.reference or self.provisional_reference
        if reference is not None:
            # |M (x - b)| = F on the ellipsoid; its mean radius in raw units is F / det(M)^(1/3).
            det = float(np.linalg.det(reference.matrix))
            return reference.field_strength / det ** (1.0 / 3.0)
        return _sphere_radius(self._points[: self._fill])

    def coverage(self) -> Coverage:
        """Share of equal-area direction cells occupied, after centring/whitening (N-free).

        The shell is checked against ``readings``: a still sensor's noise rim is no coverage.
        """
        return direction_coverage(
            self.samples, self.reference or self.provisional_reference, self.readings
        )

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
        self._record_reading(x)
        outcome = self._admit(x)
        if outcome != 'duplicate' and self.self_reference and self._fill == self._capacity:
            self._since_self_fit += 1
            if self._since_self_fit >= self._self_fit_period:  # amortised: <= 1 fit per N
                self.refresh_provisional_reference()
        return outcome

    def _record_reading(self, x: np.ndarray) -> None:
        """Reservoir sampling (Algorithm R) over a population capped at READING_HORIZON."""
        self._screened += 1
        if self._screened <= READING_SAMPLE_SIZE:
            self._readings[self._screened - 1] = x
            return
        slot = int(self._draw.random() * min(self._screened, READING_HORIZON))
        if slot < READING_SAMPLE_SIZE:
            self._readings[slot] = x

    def _admit(self, x: np.ndarray) -> str:
        """The brief's rule for a screened sample; a sample that is not unique is merged."""
        n = self._fill
        if n == 0:
            self._store(0, x)
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
        if self._provisional is not None:
            self._merge(nearest, x)
            self.merged += 1
        return 'not_unique'

    def _merge(self, slot: int, x: np.ndarray) -> None:
        """Add reading ``x`` to ``slot``'s count, sum and second moment (about the anchor, so
        a large hard-iron offset costs no precision). Plain floats: this runs per sample."""
        a0, a1, a2 = self._points[slot].tolist()
        x0, x1, x2 = x.tolist()
        d0, d1, d2 = x0 - a0, x1 - a1, x2 - a2
        self._counts[slot] += 1.0
        self._sums[slot] += (d0, d1, d2)
        self._moments[slot] += (d0 * d0, d0 * d1, d0 * d2, d1 * d1, d1 * d2, d2 * d2)

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
        problem = reading_problem(x0, x1, x2, self.full_scale)
        if problem is not None:
            return problem
        outlier = False
        window = max(100, self._capacity)
        if self._external is not None:
            verdict = self._external.check((x0, x1, x2), window)
            if verdict is None:  # stale: the sensor no longer matches it
                self.reference_drops += 1
                self._external = None
            outlier = bool(verdict)
        if self._provisional is not None:
            verdict = self._provisional.check((x0, x1, x2), window)
            if verdict is None:
                self._provisional = None
                self._since_self_fit = 0
                self._self_fit_period = self._capacity
            outlier = outlier or bool(verdict)
        return 'magnitude_outlier' if outlier else None

    # -- the provisional reference ----------------------------------------------------------------

    def refresh_provisional_reference(self) -> FitResult | None:
        """Fit the buffer (weighted by counts) and adopt a sane result as provisional reference.

        ``add`` calls this once the buffer is full, every ``capacity`` samples while the result
        keeps moving, less often (up to :data:`MAX_SELF_FIT_PERIOD` x ``capacity``) once it has
        settled; callers may call it too. Sane means determined and plausible (the condition and
        axis-ratio gates of :data:`SELF_REFERENCE_OPTIONS`) and describing most of the buffer (a
        majority of inliers), even if the coverage, sample-count or residual gates fail: it
        only judges magnitudes, with a tolerance that grows with its residual (a uniqueness
        buffer keeps the noisiest readings, so at 4 % noise its residual alone exceeds the 5 %
        gate). The tolerance is ``outlier_threshold`` sigmas, capped at ``magnitude_tolerance``:
        the robust sigma of one reading (a point of count n has sqrt(n) less noise) combined
        with the fit's own uncertainty, so an early fit from part of the sphere does not refuse
        the good readings of a region it extrapolates to (measured: 19 good readings of 3,000
        refused in one benchmark scenario without it, none with it). Buffered points it
        refuses are evicted. Returns the fit, or None when the buffer is too small to fit.
        """
        self._since_self_fit = 0
        if self._fill < max(2 * self._k, 10):
            return None
        options = SELF_REFERENCE_OPTIONS
        self.self_fits += 1
        counts = self.counts
        result = fit_calibration(self.samples, options, weights=counts)
        metrics, calibration = result.metrics, result.calibration
        sane = (
            calibration is not None
            and metrics.condition_number <= options.max_condition
            and metrics.axis_ratio <= options.max_axis_ratio
            and 2 * metrics.n_inliers > metrics.n_samples
        )
        if not sane:
            self._self_fit_period = self._capacity
            return result
        screen = _MagnitudeScreen(calibration, self.magnitude_tolerance)
        deviation = screen.relative(self.samples) - 1.0
        sigma = robust_sigma(deviation * np.sqrt(counts))  # of one reading
        spread = math.hypot(sigma, _prediction_sigma(result))
        screen.tolerance = min(options.outlier_threshold * spread, self.magnitude_tolerance)
        previous = self._provisional
        if previous is not None:
            screen.carry_window(previous)
        settled = previous is not None and not _moved(previous.calibration, calibration, sigma)
        self._self_fit_period = (
            min(2 * self._self_fit_period, MAX_SELF_FIT_PERIOD * self._capacity)
            if settled else self._capacity
        )  # fmt: skip
        self._provisional = self._projection = screen
        self._evict_outliers(screen)
        return result

    # -- reference, size, reset ----------------------------------------------------------------

    def set_reference(self, calibration: Calibration | None) -> int:
        """Use ``calibration`` to refuse gross magnitude outliers (None: stop doing so).

        Buffered samples that the new reference shows to be outliers are evicted at once, so a
        spike that got in before any calibration existed does not survive; returns how many.
        When most of the buffer disagrees with the reference, nothing is evicted: the buffer
        and the reference describe different situations, and new samples decide (see
        :data:`STALE_REFERENCE_SHARE`). A reference that moved little (online tracking) keeps
        the outlier statistics gathered under the previous one. Independent of the provisional
        reference the buffer makes itself (both screen).
        """
        previous = self._external
        if calibration is None:
            self._external = None
            return 0
        screen = _MagnitudeScreen(calibration, self.magnitude_tolerance)
        if previous is not None and not _moved(
            previous.calibration, calibration, 0.5 * self.magnitude_tolerance
        ):
            screen.carry_window(previous)
        self._external = screen
        return self._evict_outliers(screen)

    def _evict_outliers(self, screen: _MagnitudeScreen) -> int:
        """Remove the buffered points ``screen`` refuses, unless most of the buffer would go."""
        if self._fill == 0:
            return 0
        relative = screen.relative(self.samples)
        keep = np.abs(relative - 1.0) <= screen.tolerance
        removed = int(self._fill - np.count_nonzero(keep))
        if removed == 0 or removed > STALE_REFERENCE_SHARE * self._fill:
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
        self._since_self_fit = 0
        self._self_fit_period = self._capacity

    def _per_point(self) -> tuple[np.ndarray, ...]:
        """Every per-point array but the neighbour lists (those are rebuilt)."""
        return self._points, self._counts, self._sums, self._moments

    def _reallocate(self, capacity: int, k: int) -> None:
        n = self._fill
        saved = [array[:n].copy() for array in self._per_point()]
        self._allocate(capacity, k)
        self._fill = n
        for array, values in zip(self._per_point(), saved, strict=True):
            array[:n] = values
        self._refresh_all()

    def clear(self) -> None:
        """Forget every sample and counter; keeps capacity, k, full scale and the reference.

        The provisional reference goes too: it described the samples forgotten.
        """
        self._fill = 0
        self._counts.fill(0.0)
        self._projection = None
        self._nbr_dist.fill(np.inf)
        self._nbr_index.fill(-1)
        self._kth.fill(np.inf)
        self._score.fill(np.inf)
        self._weakest, self._weakest_score = 0, math.inf
        self._seen = 0
        self._screened = 0
        self._draw = random.Random(0)
        self._rejects = dict.fromkeys(REJECT_REASONS, 0)
        self.evicted = 0
        self.merged = 0
        self.self_fits = 0
        self._provisional = None
        self._since_self_fit = 0
        self._self_fit_period = self._capacity
        if self._external is not None:
            self._external.carry_window(None)

    # -- neighbour bookkeeping -----------------------------------------------------------------

    def _place(self, slot: int, x: np.ndarray, distances: np.ndarray) -> None:
        """Store ``x`` in ``slot`` (append or replace); ``distances``: x to the old rows."""
        n_before = self._fill
        n_after = max(n_before, slot + 1)
        if n_after - 1 <= self._k:  # still filling the first k + 1: every row changes
            self._store(slot, x)
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
        if slot < n_before and self._provisional is not None:
            self._fold_displaced(slot)
        self._store(slot, x)
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

    def _store(self, slot: int, x: np.ndarray) -> None:
        self._points[slot] = x
        self._counts[slot] = 1.0
        self._sums[slot] = 0.0
        self._moments[slot] = 0.0

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


class _MagnitudeScreen:
    """Refuses readings whose corrected magnitude is off a reference by more than ``tolerance``
    (relative), and tells when most of a window of readings disagree (the reference is stale)."""

    def __init__(self, calibration: Calibration, tolerance: float) -> None:
        self.calibration = calibration
        self.matrix = calibration.matrix / calibration.field_strength  # unit radius
        self.inverse = np.linalg.inv(self.matrix)
        self.offset = calibration.offset.copy()
        self._matrix = self.matrix.tolist()
        self._inverse = self.inverse.tolist()
        self._offset = self.offset.tolist()
        self.tolerance = tolerance
        self.checked = 0
        self.outliers = 0

    def carry_window(self, previous: _MagnitudeScreen | None) -> None:
        """Continue the previous screen's window (None: start a new one)."""
        self.checked = 0 if previous is None else previous.checked
        self.outliers = 0 if previous is None else previous.outliers

    def whiten(self, x: Sequence[float]) -> list[float]:
        """``M (x - b) / F`` in plain floats (numpy costs microseconds per call on 3-vectors)."""
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

    def check(self, x: Sequence[float], window: int) -> bool | None:
        """True for an outlier, False if not, None once a window shows the reference is stale."""
        outlier = not abs(math.hypot(*self.whiten(x)) - 1.0) <= self.tolerance
        self.checked += 1
        self.outliers += outlier
        if self.checked >= window:
            stale = self.outliers > STALE_REFERENCE_SHARE * self.checked
            self.checked = self.outliers = 0
            if stale:
                return None
        return outlier


def _prediction_sigma(result: FitResult) -> float:
    """Rough 1-sigma of the relative magnitude a fit predicts (its parameter uncertainty).

    |δ|u|| <= |δb| / R + ||δM|| R / F for unit-radius u; std norms stand in for the worst
    direction. Infinite when the fit reported no standard deviations.
    """
    std, metrics = result.metrics.parameter_std, result.metrics
    if not std or result.calibration is None or not metrics.mean_radius > 0.0:
        return math.inf
    offset = std.get('offset', std.get('offset_in_plane'))
    if 'matrix' in std:
        matrix = float(np.linalg.norm(std['matrix'])) * metrics.mean_radius
        matrix /= result.calibration.field_strength
    else:
        matrix = float(np.linalg.norm(std.get('matrix_in_plane_relative', [math.inf])))
    if offset is None:
        return math.inf
    return float(np.linalg.norm(offset)) / metrics.mean_radius + matrix


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
