# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field learned from readings: ``K u + c (T - T0)`` by least squares.

Stateless maths, no memory (the live bookkeeping is ``live/compensation.py``). The readings'
field is explained by the calibration's static part and the robot's own field::

    |M (raw - b - db - K u - c (T - T0))| = F        for every reading

whatever the orientation (the magnitude constraint: the Earth's field has one strength, so
what changes ``|corrected|`` with the inputs is the robot's). ``M`` and ``b`` come from the
calibration in force; ``db`` (the offset at u = 0, T = T0: a static fit made while a current
flowed holds ``K u`` in its offset), ``K``, ``c`` and ``F`` are fitted by Gauss-Newton, with
their standard errors from the residuals. A term is *determined* once its uncertainty over the
range its input took is small against the field (``DETERMINED_PCT``), and *significant* when
it stands out of that uncertainty (``SIGNIFICANT_SIGMA``): only significant, determined terms
are kept, so noise never becomes a coefficient. What kept a term undetermined is said in words
a user can act on (the input did not vary; it varied while the robot faced one way).

The magnitude needs no IMU, but sees a term only where the field's direction moves through the
sensor while the input changes. With the gyroscope (``attitudes``) the readings' changes that
orientation does not explain say it directly: two readings ``PAIR_LAGS_S`` apart between which
the robot turned little (driving straight, standing with its motors running, ArduPilot's
compassmot) differ by the gyroscope's rotation of the field plus ``K du + c dT``, so one speed
change determines all three axes of ``K`` whichever way the robot faces.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from mag_calibrator_ros.calibration.fit.calibration import Calibration, Compensation
from mag_calibrator_ros.calibration.fit.robust import mad_sigma

DETERMINED_PCT = 1.0
"""An axis of a term is determined once 1 sigma of its field over the range its input took (5th
to 95th percentile) is below this share of the field strength, in percent (a term is determined
when one of its axes is; the others are left at zero): 0.5 uT at 50 uT, about
1.4 degrees of heading at a 20 uT horizontal field at worst (the estimate is usually far better
than this bound by the time the input has varied while the robot turned)."""
SIGNIFICANT_SIGMA = 5.0
"""A determined term is kept when its coefficients stand this many standard errors out of zero
(Mahalanobis distance over its three axes): noise alone passes it about once in 10^4 fits."""
MIN_READINGS = 200
"""Fewer readings determine nothing worth adopting."""
ITERATIONS = 8
COEFFICIENT_PRIOR = 0.5
"""A term's field over its input's span: 1 sigma of half the field. Broad, so anything the
readings see is theirs; an axis they do not see (the vertical, turning in a plane) stays zero
instead of taking any value (and is reported unobserved: OBSERVED)."""
OBSERVED = 0.3
"""An axis of a term is observed when its standard error is below this share of its prior's."""
OFFSET_PRIOR = 0.1
"""The offset change's prior (at the readings' mean inputs with pairs): 1 sigma of a tenth of
the field. A robot turning in a plane does not determine the offset along the plane's normal
apart from the field strength; the static fit put it within a few percent, and the prior keeps
it there instead of letting it drift."""
ANCHOR_PRIOR = 1.0
"""Where a calibration from a file is right is unknown: each input's value there is found from
the magnitudes (``_anchored``), with a prior of 1 sigma of the larger of the input's span and
its mean over the readings (a file made with the motors off, a hover at 10 A) around that
mean. Three times that let a warm-up's term and the current's trade 18 degC against 1.7 A
along what the magnitudes of one heading cannot tell (the quick procedure on a file)."""

OFFSET_SEEN_DEG = 0.5
"""With gyroscope pairs, the offset changes only along directions the field's direction spread
over by this much (root mean square of its component over the readings) beyond twice what the
noise scatters it by: along the others (every direction but the field's, for a robot standing
still, whose K the pairs determine) the offset would slide around the sphere |corrected| = F
to wherever the noise's sample happens to scatter least (tens of uT, measured). Without pairs
no term is determined unless the field turned (MIN_TURN_DEG), and the offset stays free."""
MIN_TEMPERATURE_SPAN = 2.0
"""Degrees Celsius: a narrower span is reported as 'did not vary' without a fit of c."""
TEMPERATURE = 'temperature'
"""The name of the temperature term in reports."""
ALIKE_CORRELATION = 0.995
"""Two inputs whose samples correlate beyond this never varied independently (two topics of one
battery's current, a current and a speed it follows exactly)."""
PAIR_LAGS_S = (1.0, 3.0)
"""Readings compared through the gyroscope are this far apart (up to PAIR_SLACK times): long
enough for a speed change to reach the current, short enough that a gyroscope bias of 0.2 deg/s
turns a 50 uT field by under 0.5 uT between them."""
PAIR_SLACK = 1.5
PAIR_MAX_TURN_DEG = 2.0
"""Only readings between which the robot turned at most this much are compared: a wrong frame
of the gyroscope against the magnetometer, its scale error and the stamps' offset all scale
with the turn (2 degrees of a 50 uT field: 1.7 uT at the very worst)."""
MIN_TURN_DEG = 20.0
"""Without gyroscope pairs, the magnitude determines a term only once the field's direction in
the sensor turned this far (95th percentile from its mean) over the readings: held one way, a
current's field across the Earth's changes |corrected| only in second order, which a fit
can match by any of a circle of coefficients."""
LEARNED = ('compensation_time', 'compensation_removed_pct', 'compensation_readings',
           'compensation_interference_pct')
"""Metadata of a learned compensation, carried with it into later static fits."""
INTERFERENCE_GRADES = ((30.0, 'fine'), (60.0, 'grey zone, it may do'))
"""ArduPilot's scale for the own field (its wiki, "Advanced Compass Setup", CompassMot: under
30 % of the Earth's field acceptable, 31-60 % a grey zone, above 60 % move the compass away
from the power wires, ESCs and motors, or use an external one)."""


@dataclass(frozen=True)
class CompensationData:
    """Readings with their inputs, picklable: what one fit needs (``live/compensation.py``)."""

    raw: np.ndarray
    """(n, 3) raw readings, the calibration's units."""
    inputs: np.ndarray
    """(n, k) interference inputs (k may be 0)."""
    temperatures: np.ndarray | None
    """(n,) degrees Celsius, or None without a temperature."""
    names: tuple[str, ...] = ()
    held_raw: np.ndarray | None = None
    held_inputs: np.ndarray | None = None
    held_temperatures: np.ndarray | None = None
    """Held-out readings no fit sees, to judge the fit on (same columns)."""
    reference_temperature: float | None = None
    """T0 in degrees Celsius (None: the readings' median, rounded to 0.1)."""
    times: np.ndarray | None = None
    attitudes: np.ndarray | None = None
    held_times: np.ndarray | None = None
    held_attitudes: np.ndarray | None = None
    """Stream seconds (n,) and (n, 5) gyroscope attitudes: a stretch number and the quaternion
    (x, y, z, w) integrated within it (NaN: no gyroscope then); None without an IMU."""
    anchor: np.ndarray | None = None
    """(k + 1,): the inputs and the temperature at which the calibration in force is right for
    raw readings (zero where it compensates the term, else e.g. the mean of those of the
    readings its static fit saw; NaN: unknown; ``live/compensation.py`` carry). With gyroscope
    pairs the offset is held there along what the readings do not tell (default: at the
    readings' mean inputs). Held at the wrong inputs, a K learned standing or driving straight
    would move the offset by K times their difference."""
    anchor_unknown: bool = False
    """The calibration in force came from elsewhere (a file, parameters): where it is right is
    not known for the terms whose ``anchor`` is NaN, and with gyroscope pairs the offset is
    placed where the magnitudes put them (``_anchored``) rather than at the readings' mean."""
    temperature_term: tuple[tuple[float, float, float], float] | None = None
    """(c, T0) kept as they are: the fit learns the inputs' K only, and the readings come
    without that drift (``~/learn_compensation``: a few degrees of warm-up tell no c)."""


@dataclass(frozen=True)
class TermReport:
    """One term (an interference input, or the temperature): how well it is known."""

    name: str
    span: float
    """The range its input took (5th to 95th percentile), in its units."""
    effect_pct: float
    """Its field over that range, % of the field strength (0 when not fitted)."""
    sigma_pct: float
    """1 sigma of that field, % of the field strength (inf when not determined at all)."""
    significance: float
    """Mahalanobis distance of its coefficients from zero."""
    determined: bool
    significant: bool
    need: str = ''
    """What motion or wait would determine it ('' once determined)."""


@dataclass(frozen=True)
class CompensationFit:
    """A compensation fit: the calibration it makes, how each term is known, and its evidence."""

    calibration: Calibration | None
    """The base calibration with the kept terms and the new offset; None when nothing is kept."""
    terms: tuple[TermReport, ...] = ()
    readings: int = 0
    residual_pct: float = math.nan
    """RMS of ``|corrected| - F`` over the fitted readings with the kept terms, % of F."""
    held_current_pct: float = math.nan
    held_candidate_pct: float = math.nan
    """Spread of ``|corrected|`` on the held-out readings (RMS about its median, % of F): the
    calibration in force and the candidate."""
    removed_pct: float = 0.0
    """RMS of the compensation's field over the readings, % of F: the share it removes."""
    reason: str = ''
    kept: tuple[str, ...] = field(default_factory=tuple)
    pairs: int = 0
    """Pairs of readings compared through the gyroscope (turned at most PAIR_MAX_TURN_DEG)."""
    held_pair_errors: tuple[np.ndarray, np.ndarray] | None = None
    """The held-out pairs' ``|difference not explained by the rotation|/F``: the calibration
    in force and the candidate (``evidence.compare_residuals`` judges them)."""


def interference_pct(terms: tuple[TermReport, ...], kept: tuple[str, ...]) -> float | None:
    """The field the kept inputs (not the temperature: the sensor's drift) cause over their
    ranges, together at worst, % of the field strength F: what ArduPilot's compassmot reports as
    interference at full throttle (of the total field; a planar calibration's F is the
    horizontal field, so its share is larger, and is the one its heading feels). None without
    a kept input."""
    effects = [term.effect_pct for term in terms if term.name in kept and term.name != TEMPERATURE]
    return float(sum(effects)) if effects else None


def interference_grade(pct: float) -> str:
    """``pct`` of the field strength on ArduPilot's scale (INTERFERENCE_GRADES)."""
    for bound, grade in INTERFERENCE_GRADES:
        if pct <= bound:
            return grade
    return 'too much: move the magnetometer away from the currents, or them from it'


@dataclass(frozen=True)
class GyroPairs:
    """Readings compared through the gyroscope: ``first``/``second`` index them, ``maps``
    (p, 3, 3) carries a world-fixed vector in the IMU frame at ``first`` to the frame at
    ``second``."""

    first: np.ndarray
    second: np.ndarray
    maps: np.ndarray

    def __len__(self) -> int:
        return len(self.first)


NO_PAIRS = GyroPairs(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3, 3)))


def gyro_pairs(times: np.ndarray | None, attitudes: np.ndarray | None) -> GyroPairs:
    """Each reading with the first one each of PAIR_LAGS_S later (at most PAIR_SLACK times
    that) in the same stretch of gyroscope attitude, when the robot turned at most
    PAIR_MAX_TURN_DEG between them."""
    if times is None or attitudes is None or len(times) < 2:
        return NO_PAIRS
    times = np.asarray(times, dtype=float)
    attitudes = np.asarray(attitudes, dtype=float).reshape(len(times), 5)
    known = np.all(np.isfinite(attitudes), axis=1)
    firsts, seconds = [], []
    for lag in PAIR_LAGS_S:
        second = np.searchsorted(times, times + lag)
        first = np.arange(len(times))
        inside = second < len(times)
        first, second = first[inside], second[inside]
        keep = ((times[second] - times[first] <= lag * PAIR_SLACK) & known[first]
                & known[second] & (attitudes[first, 0] == attitudes[second, 0]))
        firsts.append(first[keep])
        seconds.append(second[keep])
    first, second = np.concatenate(firsts), np.concatenate(seconds)
    if not len(first):
        return NO_PAIRS
    from scipy.spatial.transform import Rotation  # here: a node starts without scipy.spatial

    start, end = (Rotation.from_quat(attitudes[index, 1:]) for index in (first, second))
    turn = start.inv() * end
    small = turn.magnitude() <= math.radians(PAIR_MAX_TURN_DEG)
    if not np.any(small):
        return NO_PAIRS
    maps = turn[small].inv().as_matrix()  # e_second = R_end^T R_start e_first
    return GyroPairs(first[small], second[small], maps)


def pair_evidence(current: Calibration, candidate: Calibration, raw: np.ndarray,
                  inputs: np.ndarray | None, temperatures: np.ndarray | None, pairs: GyroPairs
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``|unexplained| / F`` under both calibrations, on the pairs where they predict the change
    between the two readings differently by at least the candidate's typical error: a pair
    between which no input changed says nothing of K and would only dilute the judgement. The
    choice depends on the inputs only (the static part is shared), never on which one fits."""
    now, new = (_unexplained(calibration, raw, inputs, temperatures, pairs)
                for calibration in (current, candidate))
    errors = [np.linalg.norm(now, axis=1) / current.field_strength,
              np.linalg.norm(new, axis=1) / candidate.field_strength]
    apart = np.linalg.norm(now - new, axis=1) / candidate.field_strength
    telling = apart >= float(np.median(errors[1]))
    return errors[0][telling], errors[1][telling]


def _unexplained(calibration: Calibration, raw: np.ndarray, inputs: np.ndarray | None,
                 temperatures: np.ndarray | None, pairs: GyroPairs) -> np.ndarray:
    """``corrected_second - map corrected_first`` per pair (p, 3): what the rotation does not
    explain (zero for a perfect calibration and gyroscope)."""
    corrected = calibration.apply(raw, inputs, temperatures)
    return corrected[pairs.second] - np.einsum('pab,pb->pa', pairs.maps, corrected[pairs.first])


def _span(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    if len(finite) < 2:
        return 0.0
    low, high = np.percentile(finite, (5.0, 95.0))
    return float(high - low)


def _centre(columns: np.ndarray, pairs: GyroPairs, anchor: np.ndarray | None) -> np.ndarray:
    """Where the offset is fitted (``_solve``): with pairs, at ``anchor`` where the calibration
    in force is right (NaN: at the readings' mean inputs), not at zero current, which it may
    never have seen; else at zero."""
    centre = np.zeros(columns.shape[1])
    if len(pairs) and columns.shape[1]:
        centre = columns.mean(axis=0)
        if anchor is not None:
            centre = np.where(np.isfinite(anchor), anchor, centre)
    return centre


def _solve(raw: np.ndarray, columns: np.ndarray, spans: list[float], base: Calibration,
           pairs: GyroPairs = NO_PAIRS, anchor: np.ndarray | None = None, hold: bool = False
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton for ``|M (raw - b - d - W z)| = F``, ``z`` = (1, columns...): the offset
    change ``d`` (at zero input) is W's first column; ``M``, ``b``
    and ``F`` are the base's. With gyroscope ``pairs``, also ``A (y2 - W z2) = map A (y1 -
    W z1)`` (``A = R M``, ``y = raw - b``: the field the gyroscope says turned), weighted by
    its own noise, with the columns centred (``_centre``); ``hold`` keeps the offset there
    (OFFSET_SEEN_DEG). Returns W (3, m), its covariance (3m, 3m) in the order of
    ``W.reshape(-1)``, which of those the readings observed (OBSERVED) and the magnitude
    residuals.

    ``F`` and ``M`` stay fixed: with ``F`` free, a large offset along an axis the readings
    barely move in (the vertical of a robot turning in a plane) shrinks every other variation of
    ``|corrected|`` and fits better than the truth; with ``M`` free, each adoption could walk
    the soft iron along what the readings do not determine (refinement refits ``M`` on the
    compensated readings instead). Every coefficient has a broad prior around zero
    (OFFSET_PRIOR, COEFFICIENT_PRIOR), so what the readings cannot see stays near zero."""
    n, m = len(raw), columns.shape[1] + 1
    centre = _centre(columns, pairs, anchor)
    z = np.hstack([np.ones((n, 1)), columns - centre])
    scale = np.maximum(np.abs(z).max(axis=0), 1e-12)  # column scaling for conditioning
    zs = z / scale
    matrix, strength = base.matrix, base.field_strength
    y = raw - base.offset
    w = np.zeros((3, m))  # in scaled units
    weights = np.ones(n)
    sigmas = np.array([OFFSET_PRIOR] + [COEFFICIENT_PRIOR * scale[j] / max(spans[j - 1], 1e-300)
                                        for j in range(1, m)]) * strength
    prior = np.tile(1.0 / sigmas ** 2, 3)  # precision of the prior, by w.reshape(-1)
    precision = np.diag(prior)
    offset_axes = np.arange(3) * m  # d's entries in w.reshape(-1)
    correction = base.rotation @ matrix
    mapped = pairs.maps @ correction  # (p, 3, 3)
    zi, zj = zs[pairs.first], zs[pairs.second]
    # d(pair residual)/dW[a, c] = -A[k, a] zj[c] + (map A)[k, a] zi[c]: linear, fixed
    pair_jacobian = (-correction[None, :, :, None] * zj[:, None, None, :]
                     + mapped[:, :, :, None] * zi[:, None, None, :]).reshape(-1, 3 * m)
    pair_weights = np.ones(len(pairs))
    for iteration in range(2 * ITERATIONS):
        corrected = (y - zs @ w.T) @ matrix.T
        if iteration == ITERATIONS and hold and len(pairs):  # the own field fitted out
            precision[np.ix_(offset_axes, offset_axes)] = _offset_precision(corrected,
                                                                            sigmas[0])
        magnitude = np.linalg.norm(corrected, axis=1)
        residuals = magnitude - strength
        mad = mad_sigma(residuals)
        noise2 = max(mad, 1e-9 * strength) ** 2
        if iteration >= 2:  # robust after the first steps: readings far out weigh little
            limit = 4.0 * math.sqrt(noise2)
            weights = np.minimum(1.0, limit / np.maximum(np.abs(residuals), 1e-300))
        g = (corrected / np.maximum(magnitude, 1e-300)[:, None]) @ matrix  # d|m| / d(raw)
        jacobian = -(g[:, :, None] * zs[:, None, :]).reshape(n, 3 * m)
        normal = (jacobian * weights[:, None]).T @ jacobian + noise2 * precision
        gradient = (jacobian * weights[:, None]).T @ residuals + noise2 * (
            precision @ w.reshape(-1))
        if len(pairs):
            ci, cj = y[pairs.first] - zi @ w.T, y[pairs.second] - zj @ w.T
            differences = cj @ correction.T - np.einsum('pab,pb->pa', mapped, ci)
            spread = mad_sigma(differences, about_median=False)  # expected zero
            pair_noise2 = max(spread, 1e-9 * strength) ** 2
            if iteration >= 2:
                limit = 4.0 * math.sqrt(3.0 * pair_noise2)
                pair_weights = np.minimum(1.0, limit / np.maximum(
                    np.linalg.norm(differences, axis=1), 1e-300))
            # each reading is in up to two pairs a lag: counted once, not more
            row_weights = np.repeat(pair_weights, 3) * (
                noise2 / (2.0 * len(PAIR_LAGS_S) * pair_noise2))
            normal += (pair_jacobian * row_weights[:, None]).T @ pair_jacobian
            gradient += (pair_jacobian * row_weights[:, None]).T @ differences.reshape(-1)
        step = -np.linalg.lstsq(normal, gradient, rcond=None)[0]
        w = w + step.reshape(3, m)
        if np.max(np.abs(step)) < 1e-9 * strength and iteration > ITERATIONS:
            break
    residuals = np.linalg.norm((y - zs @ w.T) @ matrix.T, axis=1) - strength
    dof = max(int(np.sum(weights)) - normal.shape[0], 1)
    sigma2 = float(np.sum(weights * residuals ** 2)) / dof
    covariance = np.linalg.pinv(normal) * sigma2
    seen = np.sqrt(np.maximum(np.diag(covariance), 0.0) * prior) < OBSERVED  # prior narrowed
    unscale = np.tile(1.0 / scale, 3)
    w = w / scale
    w[:, 0] -= w[:, 1:] @ centre  # the offset change at zero input
    return w, covariance * np.outer(unscale, unscale), seen, residuals


def _placed(raw: np.ndarray, columns: np.ndarray, gains: np.ndarray, base: Calibration,
            pairs: GyroPairs, anchor: np.ndarray, anchor_unknown: bool = False
            ) -> tuple[np.ndarray, np.ndarray]:
    """The offset change at zero input, and the residuals, with the terms ``gains`` (3, m)
    fixed as they will be used (undetermined axes zero: placed for the values the fit gave
    them, a multicopter's hover log had a candidate 35 % off on held-out readings instead of
    15 %) and the offset held where the calibration in force is right along what the readings
    do not tell (``_solve``'s hold). The terms come from the fit without the hold: with it, a
    robot that stood, then turned at another current, had every axis of K determined by that
    one step, carrying the calibration's small error along the unseen axes into K (-0.47,
    -1.12, -0.15 uT/A against a true 1.6, 0, 0, measured on the benchmark's course). With
    ``anchor_unknown``, the hold is where the magnitudes put it (``_anchored``)."""
    centre = _centre(columns, pairs, anchor)
    free = ~np.isfinite(anchor) if anchor is not None else np.ones(len(centre), dtype=bool)
    if anchor_unknown and len(pairs) and free.any():
        centre = _anchored(raw, columns, gains, base, centre, free)
    shifted = raw - (columns - centre) @ gains.T
    w, _, _, residuals = _solve(shifted, np.zeros((len(raw), 0)), [], base, pairs, hold=True)
    return w[:, 0] - gains @ centre, residuals


def _anchored(raw: np.ndarray, columns: np.ndarray, gains: np.ndarray, base: Calibration,
              centre: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
    """The inputs at which ``base`` is right, when nothing says (a calibration from a file): a
    static fit made at inputs ``a`` holds ``K a`` in its offset, so with the terms ``gains``
    (3, m) the corrected field is ``M (raw - b + K a - K u)``, and its magnitude tells ``a``
    wherever ``K`` has a component along the field. Each ``a_j`` starts at ``centre`` and stays
    near it where the magnitudes cannot tell (ANCHOR_PRIOR); only the ``free`` ones move (the
    others are known: a term the calibration compensates is right at zero). Held at the
    readings' mean instead, a file fitted with the motors idle and a drive at 2 A gave a
    learned offset 3 uT off and |B| 9 % off (mag_calibrator_fit --calibration on the quick
    procedure)."""
    m = columns.shape[1]
    if m == 0 or len(raw) == 0:
        return centre
    matrix, strength = base.matrix, base.field_strength
    without = raw - base.offset - columns @ gains.T  # the field at zero input, but for K a
    spans = np.array([_span(columns[:, j]) for j in range(m)])
    scale = ANCHOR_PRIOR * np.maximum(np.maximum(spans, np.abs(centre)), 1e-12)
    scale = np.where(np.ones(m, dtype=bool) if free is None else free, scale, 1e-9 * scale)
    anchor = centre.astype(float).copy()
    for iteration in range(2 * ITERATIONS):
        corrected = (without + anchor @ gains.T) @ matrix.T
        magnitude = np.linalg.norm(corrected, axis=1)
        residuals = magnitude - strength
        mad = mad_sigma(residuals)
        noise2 = max(mad, 1e-9 * strength) ** 2
        weights = np.ones(len(raw)) if iteration < 2 else np.minimum(
            1.0, 4.0 * math.sqrt(noise2) / np.maximum(np.abs(residuals), 1e-300))
        jacobian = ((corrected / np.maximum(magnitude, 1e-300)[:, None]) @ matrix) @ gains
        normal = (jacobian * weights[:, None]).T @ jacobian + noise2 * np.diag(scale ** -2.0)
        gradient = (jacobian * weights[:, None]).T @ residuals + noise2 * (
            anchor - centre) / scale ** 2
        step = -np.linalg.lstsq(normal, gradient, rcond=None)[0]
        anchor = anchor + step
        if np.all(np.abs(step) < 1e-9 * scale):
            break
    return anchor if np.all(np.isfinite(anchor)) else centre


def _offset_precision(corrected: np.ndarray, sigma: float) -> np.ndarray:
    """The offset change's prior precision (3, 3): ``1/sigma^2`` along the directions the
    readings' field direction spread over (OFFSET_SEEN_DEG), a million times that along the
    others (held where the calibration in force puts it)."""
    magnitude = np.linalg.norm(corrected, axis=1)
    directions = corrected / np.maximum(magnitude, 1e-300)[:, None]
    noise = mad_sigma(magnitude)
    noise /= max(float(np.median(magnitude)), 1e-300)
    spread, axes = np.linalg.eigh(np.cov(directions.T, bias=True).reshape(3, 3))
    seen = spread >= math.sin(math.radians(OFFSET_SEEN_DEG)) ** 2 + 4.0 * noise ** 2
    weights = np.where(seen, 1.0, 1e6) / sigma ** 2
    return (axes * weights) @ axes.T


def magnitude_spread_pct(calibration: Calibration, raw: np.ndarray,
                         inputs: np.ndarray | None, temperatures: np.ndarray | None) -> float:
    """RMS of ``|corrected| - F``, % of F: how far from the calibration's sphere the readings
    are with it (the held-out judgement; F is the same for the calibration in force and a
    candidate learned on it, so no candidate wins by changing the yardstick)."""
    if raw is None or len(raw) == 0:
        return math.nan
    corrected = calibration.unrotated(calibration.compensated(raw, inputs, temperatures))
    magnitude = np.linalg.norm(corrected, axis=1)
    strength = calibration.field_strength
    return 100.0 * math.sqrt(float(np.mean((magnitude - strength) ** 2))) / strength


def fit_compensation(data: CompensationData, base: Calibration) -> CompensationFit:
    """Learn ``K``, ``c`` and the offset at u = 0, T = T0 from readings; see the module.

    ``base``: the calibration in force (its static part is kept; its compensation, if any, is
    replaced); T0 is ``data.reference_temperature``, else the readings' median. Never raises on
    data: a fit that cannot be made says why in ``reason``.
    """
    raw = np.asarray(data.raw, dtype=float).reshape(-1, 3)
    inputs = np.asarray(data.inputs, dtype=float).reshape(len(raw), -1)
    names = list(data.names)
    temperatures = None if data.temperatures is None else np.asarray(data.temperatures, float)
    usable = np.all(np.isfinite(raw), axis=1) & np.all(np.isfinite(inputs), axis=1)
    if temperatures is not None:
        usable &= np.isfinite(temperatures)
    raw, inputs = raw[usable], inputs[usable]
    temperatures = None if temperatures is None else temperatures[usable]
    pairs = (NO_PAIRS if data.times is None or data.attitudes is None else
             gyro_pairs(np.asarray(data.times, float)[usable],
                        np.asarray(data.attitudes, float).reshape(-1, 5)[usable]))
    if len(raw) < MIN_READINGS:
        return CompensationFit(None, readings=len(raw),
                               reason=f'{len(raw)} readings with their inputs, '
                                      f'{MIN_READINGS} needed')
    strength = base.field_strength
    t0 = data.reference_temperature
    if temperatures is not None and t0 is None:
        t0 = round(float(np.median(temperatures)), 1)
    columns, spans, labels = [], [], []
    for j, name in enumerate(names):
        spans.append(_span(inputs[:, j]))
        columns.append(inputs[:, j])
        labels.append(name)
    if temperatures is not None:
        spans.append(_span(temperatures))
        columns.append(temperatures - t0)
        labels.append(TEMPERATURE)
    reports: list[TermReport] = []
    directions = base.unrotated(raw)
    directions /= np.maximum(np.linalg.norm(directions, axis=1), 1e-300)[:, None]
    mean = directions.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-300)
    turned_deg = float(np.degrees(np.arccos(np.clip(np.percentile(directions @ mean, 5.0),
                                                     -1.0, 1.0))))
    varied = [index for index, span in enumerate(spans)
              if span > 0 and (labels[index] != TEMPERATURE or span >= MIN_TEMPERATURE_SPAN)]
    alike = _alike(columns, labels, varied)
    varied = [index for index in varied if index not in alike]
    design = np.stack([columns[i] for i in varied], axis=1) if varied else np.zeros((len(raw), 0))
    anchors = np.full(len(labels), math.nan)
    if data.anchor is not None and len(data.anchor) == len(names) + 1:
        anchors[:len(names)] = np.asarray(data.anchor, float)[:len(names)]
        if temperatures is not None:
            anchors[-1] = float(data.anchor[-1]) - t0
    w, covariance, seen, _ = _solve(raw, design, [spans[i] for i in varied], base, pairs,
                                    anchors[varied])
    determined_axes: dict[int, np.ndarray] = {}
    m = design.shape[1] + 1
    kept: list[int] = []
    for index, label in enumerate(labels):
        if index not in varied:
            reports.append(TermReport(label, spans[index], 0.0, math.inf, 0.0, False, False,
                                      alike.get(index) or _need(label, spans[index], False)))
            continue
        column = varied.index(index) + 1
        picks = np.array([axis * m + column for axis in range(3)])
        axis_sigma = np.sqrt(np.maximum(np.diag(covariance)[picks], 0.0)) * spans[index]
        axes = seen[picks] & (100.0 * axis_sigma / strength <= DETERMINED_PCT) & (
            bool(len(pairs)) or turned_deg >= MIN_TURN_DEG)
        determined_axes[index] = axes  # the vertical of a robot turning level is not among them
        coefficients = w[axes, column]
        block = covariance[np.ix_(picks[axes], picks[axes])]
        sigma = (math.sqrt(float(np.sum(axis_sigma[axes] ** 2))) if axes.any()
                 else float(np.min(axis_sigma)))
        effect = float(np.linalg.norm(coefficients)) * spans[index]
        try:
            significance = math.sqrt(max(float(coefficients @ np.linalg.solve(
                block, coefficients)), 0.0))
        except np.linalg.LinAlgError:
            significance = 0.0
        sigma_pct = 100.0 * sigma / strength
        determined = bool(axes.any())
        significant = determined and significance >= SIGNIFICANT_SIGMA
        if significant:
            kept.append(index)
        reports.append(TermReport(label, spans[index], 100.0 * effect / strength, sigma_pct,
                                  significance, determined, significant,
                                  _need(label, spans[index], True) if not determined else ''))
    # The calibration: refit with the kept terms only (the others are noise or unknown), then
    # place the offset with them fixed (``_placed``).
    design = (np.stack([columns[i] for i in kept], axis=1) if kept
              else np.zeros((len(raw), 0)))
    w, _, _, residuals = _solve(raw, design, [spans[i] for i in kept], base, pairs,
                                anchors[kept])
    if len(pairs) and kept:
        for position, index in enumerate(kept):  # placed for the terms as they will be used
            w[~determined_axes[index], position + 1] = 0.0
        w[:, 0], residuals = _placed(raw, design, w[:, 1:], base, pairs, anchors[kept],
                                     data.anchor_unknown)
    gains = np.zeros((3, len(names)))
    drift = np.zeros(3)
    for position, index in enumerate(kept):
        values = np.where(determined_axes[index], w[:, position + 1], 0.0)  # unknown: none
        if labels[index] == TEMPERATURE:
            drift = values
        else:
            gains[:, index] = values
    residual_pct = 100.0 * math.sqrt(float(np.mean(residuals ** 2))) / strength
    fit = CompensationFit(None, tuple(reports), len(raw), residual_pct,
                          kept=tuple(labels[i] for i in kept), pairs=len(pairs))
    if not kept:
        return _with_reason(fit, reports, bool(len(pairs)))
    if temperatures is None and data.temperature_term is not None:
        drift, t0 = np.asarray(data.temperature_term[0], float), data.temperature_term[1]
    compensation = Compensation(tuple(names), gains, drift,
                                t0 if np.any(drift) else None)
    offset = base.offset + w[:, 0]
    candidate = base.with_compensation(compensation, offset=offset)
    own = compensation.field(inputs, temperatures) - np.mean(
        compensation.field(inputs, temperatures), axis=0)
    removed = 100.0 * math.sqrt(float(np.mean(np.sum(own ** 2, axis=1)))) / strength
    held = data.held_raw is not None and len(data.held_raw) > 0
    current_pct = candidate_pct = math.nan
    held_pair_errors = None
    if held:
        held_inputs = (None if data.held_inputs is None
                       else np.asarray(data.held_inputs, float).reshape(len(data.held_raw), -1))
        current_pct = magnitude_spread_pct(base, data.held_raw, held_inputs,
                                           data.held_temperatures)
        candidate_pct = magnitude_spread_pct(candidate, data.held_raw, held_inputs,
                                             data.held_temperatures)
        held_pairs = gyro_pairs(data.held_times, data.held_attitudes)
        if len(held_pairs):
            held_pair_errors = pair_evidence(base, candidate, data.held_raw, held_inputs,
                                             data.held_temperatures, held_pairs)
    return CompensationFit(candidate, tuple(reports), len(raw), residual_pct, current_pct,
                           candidate_pct, removed, kept=tuple(labels[i] for i in kept),
                           pairs=len(pairs), held_pair_errors=held_pair_errors)


def _alike(columns: list[np.ndarray], labels: list[str], varied: list[int]) -> dict[int, str]:
    """The inputs that varied only with an earlier one (correlation beyond ALIKE_CORRELATION),
    each with the words saying so: their fields cannot be told apart, and a fit of both found
    any K1 = -K2 as good as the truth (issue #47); the earlier one is fitted alone."""
    alike: dict[int, str] = {}
    for position, index in enumerate(varied):
        for earlier in varied[:position]:
            if earlier in alike or labels[index] == TEMPERATURE:
                continue
            correlation = float(np.corrcoef(columns[earlier], columns[index])[0, 1])
            if abs(correlation) >= ALIKE_CORRELATION:
                alike[index] = (f"input '{labels[index]}' never varied apart from "
                                f"'{labels[earlier]}' (correlation {correlation:.3f}): their "
                                'fields cannot be told apart; list one of them in '
                                'interference_inputs')
                break
    return alike


def _need(label: str, span: float, varied: bool) -> str:
    """What would determine a term, for a person."""
    if label == TEMPERATURE:
        if span < MIN_TEMPERATURE_SPAN:
            return (f'the temperature varied {span:.1f} degC (at least {MIN_TEMPERATURE_SPAN:g} '
                    'needed): it is learned while the sensor warms up or cools down, so keep '
                    'the robot working from a cold start')
        return ('the temperature changed while the robot faced one way: keep turning as it '
                'warms up')
    if not varied:
        return (f"input '{label}' did not vary: drive at several speeds, stop and start, and "
                'turn in place, so the current changes')
    return (f"input '{label}' varied, but not in enough headings to tell its field from the "
            f"Earth's: {HEADINGS_NEED}")


HEADINGS_NEED = 'drive and turn at several speeds facing several directions'
GYRO_NEED = (', or pair an IMU with a gyroscope (imu/data_raw): then a change of the input while '
             'the robot drives straight or stands still tells its field directly')


def _with_reason(fit: CompensationFit, reports: list[TermReport],
                 gyroscope: bool = False) -> CompensationFit:
    needs = [report.need for report in reports if report.need]
    if not gyroscope:
        needs = [need.replace(HEADINGS_NEED, HEADINGS_NEED + GYRO_NEED) for need in needs]
    if needs:
        reason = '; '.join(needs)
    elif reports:
        reason = 'no input changes the field measurably (nothing to compensate)'
    else:
        reason = 'no interference input or temperature to learn from'
    return CompensationFit(None, fit.terms, fit.readings, fit.residual_pct, reason=reason,
                           pairs=fit.pairs)


__all__ = ['DETERMINED_PCT', 'INTERFERENCE_GRADES', 'LEARNED', 'MIN_READINGS', 'MIN_TURN_DEG',
           'NO_PAIRS', 'PAIR_LAGS_S', 'PAIR_MAX_TURN_DEG', 'SIGNIFICANT_SIGMA', 'TEMPERATURE',
           'CompensationData', 'CompensationFit', 'GyroPairs', 'TermReport', 'fit_compensation',
           'gyro_pairs', 'interference_grade', 'interference_pct', 'magnitude_spread_pct',
           'pair_evidence']
