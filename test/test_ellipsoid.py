# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ellipsoid.py's machinery: the fast path against the robust one, the solvers against scipy,
the algebraic fits against their explicit designs, block-wise passes against single ones."""

import numpy as np
import pytest
from scipy.optimize import least_squares
from test_fitting import readings, soft_iron, unit_vectors, yaw_directions

from mag_calibrator_ros.calibration.fit import ellipsoid
from mag_calibrator_ros.calibration.fit.coverage import distinct_rows
from mag_calibrator_ros.calibration.fit.ellipsoid import (
    axis_least_squares,
    fit_ellipsoid,
    fit_ellipsoids,
    quadric_least_squares,
    sphere_least_squares,
)
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration


def clean_tumble(seed, n=2000, noise=0.25):
    rng = np.random.default_rng(seed)
    soft, offset = soft_iron(rng), rng.uniform(-300.0, 300.0, 3)
    raw, _ = readings(unit_vectors(rng, n), rng, soft, offset, noise=noise)
    return raw


def assert_same_fit(a, b, rtol=1e-7):
    scale = np.max(np.abs(a.matrix))
    np.testing.assert_allclose(a.offset, b.offset, atol=rtol / scale)
    np.testing.assert_allclose(a.matrix, b.matrix, atol=rtol * scale)


# ----------------------------------------------------------------------------------------------
# fast path and robust path


@pytest.mark.parametrize('model', ['sphere', 'full'])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_clean_data_take_the_fast_path_to_the_robust_paths_fit(model, seed):
    raw = clean_tumble(seed)
    fast = fit_ellipsoid(raw, model)
    robust = fit_ellipsoid(raw, model, always_robust=True)
    assert not fast.robust and robust.robust
    assert_same_fit(fast, robust)
    # the inliers may differ only by a point on the border (4 sigma of either fit)
    assert np.count_nonzero(fast.inliers != robust.inliers) <= 1


def test_a_clean_ring_takes_the_fast_path_to_the_robust_paths_planar_fit():
    rng = np.random.default_rng(5)
    soft, offset = soft_iron(rng), np.array([60.0, -40.0, 25.0])
    raw, _ = readings(yaw_directions(rng, 400), rng, soft, offset)
    fast = fit_ellipsoid(raw, 'planar')
    robust = fit_ellipsoid(raw, 'planar', always_robust=True)
    assert not fast.robust and robust.robust
    assert_same_fit(fast, robust)


@pytest.mark.parametrize('share', [0.01, 0.03, 0.2])
def test_spikes_take_the_robust_path_and_are_all_flagged(share):
    rng = np.random.default_rng(7)
    soft, offset = soft_iron(rng), np.array([200.0, -100.0, 50.0])
    raw, spiked = readings(unit_vectors(rng, 1500), rng, soft, offset, spikes=share)
    fitted = fit_ellipsoid(raw, 'full')
    assert fitted.robust
    assert not fitted.inliers[spiked].any()
    assert_same_fit(fitted, fit_ellipsoid(raw, 'full', always_robust=True), rtol=0)


def test_heavy_tailed_disturbance_takes_the_robust_path():
    """A few per cent of moderately disturbed readings (no gross spike) bend a plain fit less
    than the spikes do; the fast path's outlier count still sends them to the robust path."""
    raw = clean_tumble(8, n=3000)
    rng = np.random.default_rng(9)
    disturbed = rng.choice(len(raw), 90, replace=False)
    raw[disturbed] *= rng.uniform(1.02, 1.06, (90, 1))
    fitted = fit_ellipsoid(raw, 'full')
    assert fitted.robust
    assert_same_fit(fitted, fit_ellipsoid(raw, 'full', always_robust=True), rtol=0)


def test_auto_shares_one_normalisation_and_gives_each_models_own_fit():
    raw = clean_tumble(10)
    together = fit_ellipsoids(raw, ('sphere', 'full'))
    for model in ('sphere', 'full'):
        alone = fit_ellipsoid(raw, model)
        assert_same_fit(together[model], alone, rtol=0)
        np.testing.assert_array_equal(together[model].inliers, alone.inliers)


@pytest.fixture
def robust_flags(monkeypatch):
    """The ``always_robust`` of every fit_ellipsoids call fit_calibration makes."""
    calls = []
    original = ellipsoid.fit_ellipsoids

    def spy(*args, **kwargs):
        calls.append(args[5] if len(args) > 5 else kwargs.get('always_robust', False))
        return original(*args, **kwargs)

    monkeypatch.setattr('mag_calibrator_ros.calibration.fit.fitting.fit_ellipsoids', spy)
    return calls


def test_a_fast_fit_near_a_gate_is_redone_on_the_robust_path(robust_flags):
    """Noise at 4.3 % of the field: the residual gate (5 %) is near, so the decision must come
    from the robust fit, exactly as if the fast path did not exist."""
    raw = clean_tumble(11, n=600, noise=0.043 * 50.0)
    result = fit_calibration(raw, FitOptions(model='full'))
    assert robust_flags == [False, True]
    unit = 2 ** round(np.log2(ellipsoid.normalise(raw).scale))
    robust = fit_ellipsoid(raw / unit, 'full', always_robust=True)
    assert result.metrics.n_inliers == int(robust.inliers.sum())


def test_a_fast_fit_far_from_every_gate_stands(robust_flags):
    result = fit_calibration(clean_tumble(12), FitOptions(model='full'))
    assert result.success and robust_flags == [False]


# ----------------------------------------------------------------------------------------------
# solvers


def ellipsoid_problem(seed, spikes=0.0):
    rng = np.random.default_rng(seed)
    raw, _ = readings(unit_vectors(rng, 500), rng, soft_iron(rng), rng.uniform(-1, 1, 3) * 50,
                      noise=0.5, spikes=spikes)
    y = ellipsoid.normalise(raw).forward(raw)
    model = ellipsoid._Geometric(y, spherical=False)
    start = model.pack(np.zeros(3), np.eye(3))
    return model, start


@pytest.mark.parametrize('seed', [20, 21, 22])
def test_least_squares_reaches_scipys_minimum(seed):
    model, start = ellipsoid_problem(seed)
    mask = np.ones(len(model.points), dtype=bool)
    weights = np.random.default_rng(seed).uniform(0.5, 3.0, len(mask))
    ours, _, _ = ellipsoid._minimise(model, start, mask, weights)

    def weighted(params):
        return model.residuals(params) * np.sqrt(weights)

    reference = least_squares(weighted, start, method='lm', xtol=1e-14, ftol=1e-14).x
    np.testing.assert_allclose(ours, reference, atol=1e-8)


@pytest.mark.parametrize('seed', [23, 24])
def test_soft_l1_reaches_scipys_robust_minimum(seed):
    model, start = ellipsoid_problem(seed, spikes=0.05)
    mask = np.ones(len(model.points), dtype=bool)
    f_scale = 0.02
    ours, _, _ = ellipsoid._minimise(model, start, mask, None, f_scale)
    reference = least_squares(model.residuals, start, loss='soft_l1', f_scale=f_scale,
                              xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    # both stop once the loss changes by less than 1e-8 of itself (scipy's default ftol, which
    # the robust stage used before): the parameters are then within about 1e-4
    np.testing.assert_allclose(ours, reference, atol=1e-4)


def test_condition_of_an_ill_conditioned_fit_is_that_of_the_jacobian_itself():
    """Motion within ±0.06° of a plane: the normal equations would square a condition of 2e6
    and lose it; the QR path must match an SVD of a finite-difference Jacobian."""
    rng = np.random.default_rng(25)
    directions = yaw_directions(rng, 400, inclination_deg=0.0)
    directions[:, 2] = rng.uniform(-0.001, 0.001, 400)
    raw, _ = readings(directions, rng, np.eye(3), np.zeros(3), noise=0.0005)
    y = ellipsoid.normalise(raw).forward(raw)
    model = ellipsoid._Geometric(y, spherical=False)
    params = model.pack(*quadric_least_squares(y))
    mask = np.ones(len(y), dtype=bool)
    condition, _ = ellipsoid._condition_and_std(model, params, mask, None, model.residuals(params))
    step = 1e-5
    jacobian = np.column_stack([
        (model.residuals(params + step * e) - model.residuals(params - step * e)) / (2 * step)
        for e in np.eye(len(params))
    ])
    singular = np.linalg.svd(jacobian, compute_uv=False)
    assert condition > ellipsoid.EXACT_CONDITION
    assert condition == pytest.approx(singular[0] / singular[-1], rel=1e-3)


# ----------------------------------------------------------------------------------------------
# algebraic fits from moments, block-wise passes


def explicit_lstsq(design, target, weights):
    root = np.sqrt(weights)
    return np.linalg.lstsq(design * root[:, None], target * root, rcond=None)[0]


@pytest.mark.parametrize('seed', [30, 31, 32])
def test_algebraic_fits_from_moments_equal_their_explicit_designs(seed):
    rng = np.random.default_rng(seed)
    y = ellipsoid.normalise(clean_tumble(seed, n=300)).forward(clean_tumble(seed, n=300))
    weights = rng.uniform(0.5, 5.0, len(y))
    x, yy, z = y.T
    # sphere: |y|² = 2 b·y + c
    solution = explicit_lstsq(np.column_stack([2 * y, np.ones(len(y))]), np.sum(y**2, axis=1),
                              weights)
    centre, radius = sphere_least_squares(y, weights)
    np.testing.assert_allclose(centre, solution[:3], atol=1e-10)
    assert radius == pytest.approx(np.sqrt(solution[3] + solution[:3] @ solution[:3]), rel=1e-10)
    # quadric: yᵀ A y + 2 gᵀ y = 1
    design = np.column_stack([x * x, 2 * x * yy, 2 * x * z, yy * yy, 2 * yy * z, z * z, 2 * y])
    solution = explicit_lstsq(design, np.ones(len(y)), weights)
    a = np.array([[solution[0], solution[1], solution[2]],
                  [solution[1], solution[3], solution[4]],
                  [solution[2], solution[4], solution[5]]])
    expected_centre = -np.linalg.solve(a, solution[6:])
    centre, matrix = quadric_least_squares(y, weights)
    np.testing.assert_allclose(centre, expected_centre, atol=1e-9)
    k = 1.0 + expected_centre @ a @ expected_centre
    np.testing.assert_allclose(matrix @ matrix, a / k, atol=1e-9)
    # axis (mag-calibrator-rs): H = [x, y, z, -y², -z², 1], w = x²
    solution = explicit_lstsq(np.column_stack([x, yy, z, -yy**2, -z**2, np.ones(len(y))]), x**2,
                              weights)
    offset, _ = axis_least_squares(y, weights)
    np.testing.assert_allclose(offset[0], solution[0] / 2, atol=1e-10)


@pytest.mark.parametrize('model', ['sphere', 'full', 'planar', 'axis'])
def test_fits_do_not_depend_on_the_block_size(monkeypatch, model):
    rng = np.random.default_rng(40)
    soft, offset = soft_iron(rng), np.array([30.0, 20.0, -10.0])
    directions = yaw_directions(rng, 700) if model == 'planar' else unit_vectors(rng, 700)
    # the axis model is plain least squares (no outlier handling): no spikes for it
    raw, _ = readings(directions, rng, soft, offset, spikes=0.0 if model == 'axis' else 0.02)
    weights = rng.uniform(1.0, 4.0, len(raw))
    fits = []
    for rows in (7, 100, 1 << 20):
        monkeypatch.setattr(ellipsoid, 'CHUNK_ROWS', rows)
        fits.append(fit_ellipsoid(raw, model, weights=weights))
    for fitted in fits[1:]:
        assert_same_fit(fitted, fits[0], rtol=1e-9)
        np.testing.assert_array_equal(fitted.inliers, fits[0].inliers)
        assert fitted.condition == pytest.approx(fits[0].condition, rel=1e-9)


def test_distinct_rows_keep_first_occurrences_in_order_like_numpy_unique():
    rng = np.random.default_rng(50)
    for _ in range(50):
        rows = rng.integers(-2, 3, size=(int(rng.integers(2, 300)), 3)).astype(float)
        rows[rng.random(len(rows)) < 0.2, 0] = -0.0  # equal to 0.0
        first = np.sort(np.unique(rows, axis=0, return_index=True)[1])
        np.testing.assert_array_equal(distinct_rows(rows), rows[first])


def test_a_cap_of_the_sphere_stops_the_fit_where_it_starts_to_walk():
    """Readings on a cap fit ever larger, flatter ellipsoids (the minimum is at infinity): the
    fit used every iteration it had walking there (100 least-squares, 50 robust; half the time
    ``mag_calibrator_fit`` took on the x-io Fusion example log), to be refused as
    ill-conditioned. It stops at the first step past DIVERGED_CONDITION (old: 5.6e3 here), and
    is refused the same."""
    rng = np.random.default_rng(5)
    directions = unit_vectors(rng, 3000)
    cap = directions[directions[:, 2] > 0.5][:300]
    raw = 50.0 * cap @ np.diag([1.05, 0.97, 1.0]).T + [30.0, -20.0, 10.0]
    raw += rng.normal(0.0, 0.3, raw.shape)
    result = fit_calibration(raw, FitOptions(model='full'))
    assert not result.success
    assert ellipsoid.DIVERGED_CONDITION < result.metrics.condition_number < (
        1.1 * ellipsoid.DIVERGED_CONDITION)
    with pytest.raises(ValueError, match='max_condition must be below 1000'):
        FitOptions(max_condition=ellipsoid.DIVERGED_CONDITION)
