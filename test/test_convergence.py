# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Refinement converges to what ``~/calibrate`` would give, and no adoption makes it worse.

A noisy sensor (2 % of the field, like the shared fxos8700 and bno055 recordings) turned for
half a minute with new noise every pass: the calibration the session puts in force by itself
ends as good as the fit a user would get by calling ``~/calibrate``. With spikes, a disturbed
stretch and a magnet passing in every pass, no calibration it adopts is worse on the true field
than the one it replaced. And /diagnostics says how far the calibration in force is from the
best fit of what the node holds.
"""

from __future__ import annotations

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.evidence import Comparison
from mag_calibrator_ros.calibration.live.findings import Findings
from mag_calibrator_ros.calibration.live.offline import calibrate_now
from mag_calibrator_ros.calibration.live.report import could_be_better
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.verdicts import COVERAGE_SLACK, coverage_kept
from mag_calibrator_ros.sim import motion

FIELD_T = 50e-6
HARD_IRON_T = np.array([120e-6, -80e-6, 60e-6])
SOFT_IRON = np.array([[1.15, 0.10, -0.08], [0.10, 0.85, 0.12], [-0.08, 0.12, 1.00]])
STEP_NS = 10_000_000  # stamped at 100 Hz, as benchmarks/bench_replay.py replays recordings


def recording(rows: int, seed: int) -> np.ndarray:
    """Noise-free raw readings of a hand tumble sampled at 10 Hz: ``rows`` readings that go
    round the sphere, like a short recording replayed at 100 Hz."""
    truth = motion.body_field_samples('tumble', rows, 10.0, FIELD_T, 60.0, seed)
    return truth @ SOFT_IRON.T + HARD_IRON_T


def with_noise(raw: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    return raw + rng.normal(0.0, noise * FIELD_T, raw.shape)


def spread(corrected: np.ndarray) -> float:
    magnitudes = np.linalg.norm(corrected, axis=1)
    return float(magnitudes.std() / magnitudes.mean())


def truth_error(calibration: Calibration, raw: np.ndarray) -> float:
    """RMS relative magnitude error on noise-free readings: what better and worse mean."""
    magnitudes = np.linalg.norm(calibration.apply(raw), axis=1) / calibration.field_strength
    return float(np.sqrt(np.mean((magnitudes - 1.0) ** 2)))


def feed(session: CalibrationSession, rows: np.ndarray, start: int) -> int:
    for index, row in enumerate(rows.tolist(), start):
        session.process(index * STEP_NS, 'imu_link', row)
        if index % 50 == 0:
            session.poll()
    return start + len(rows)


@pytest.mark.parametrize('seed', [1, 2])
def test_the_calibration_in_force_ends_as_good_as_a_requested_fit(seed):
    """Ten passes of 350 readings with fresh 2 % noise, no service call: the last pass under
    the calibration in force spreads no more than under what ``~/calibrate`` then gives (+2 %,
    the benchmark's target). With eight held-out readings a direction the session kept its
    50 %-coverage first calibration while gains of a few per cent stayed below three standard
    errors."""
    raw = recording(350, seed)
    rng = np.random.default_rng(seed)
    session = CalibrationSession()
    index, last = 0, None
    for _ in range(10):
        last = with_noise(raw, 0.02, rng)
        index = feed(session, last, index)
    live = session.calibration
    assert live is not None and session.report().counts.adoptions.get('auto') == 1
    attempt = calibrate_now(session)
    assert attempt.success, attempt.message
    requested = session.calibration
    assert requested is not live
    assert spread(live.apply(last)) <= 1.02 * spread(requested.apply(last))
    assert truth_error(live, raw) <= truth_error(requested, raw) + 0.002


def disturbed(raw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One pass with 2 % noise, 3 % spikes of 2-5 F, a tenth of the pass off by a steady 10 %
    of the field (a motor running), and a magnet passing (up to 0.8 F over a tenth)."""
    out = with_noise(raw, 0.02, rng)
    n = len(out)
    spikes = rng.random(n) < 0.03
    unit = rng.normal(size=(int(spikes.sum()), 3))
    out[spikes] += (unit / np.linalg.norm(unit, axis=1, keepdims=True)
                    * rng.uniform(2.0, 5.0, (len(unit), 1)) * FIELD_T)
    start = int(rng.integers(0, n - n // 10))
    steady = rng.normal(size=3)
    out[start:start + n // 10] += 0.1 * FIELD_T * steady / np.linalg.norm(steady)
    start, length = int(rng.integers(0, n - n // 10)), n // 10
    bump = np.sin(np.linspace(0.0, np.pi, length)) ** 2
    out[start:start + length] += bump[:, None] * 0.8 * FIELD_T * np.array([0.6, 0.0, 0.8])
    return out


@pytest.mark.parametrize('seed', [3, 4, 5])
def test_no_adoption_is_worse_on_the_true_field_with_spikes_disturbances_and_a_magnet(seed):
    """Every change of the calibration in force, watched reading by reading over ten disturbed
    passes: none is worse than the one it replaced by more than the 10 % within which noise
    and such disturbances may favour either (test_evidence's property test)."""
    raw = recording(400, seed)
    rng = np.random.default_rng(seed)
    session = CalibrationSession()
    index, errors, in_force = 0, [], None
    for _ in range(10):
        for row in disturbed(raw, rng).tolist():
            session.process(index * STEP_NS, 'imu_link', row)
            index += 1
            if index % 50 == 0:
                session.poll()
            if session.calibration is not in_force:
                in_force = session.calibration
                errors.append(truth_error(in_force, raw))
    adoptions = session.report().counts.adoptions
    assert adoptions.get('auto') == 1, adoptions
    assert errors
    for before, after in zip(errors, errors[1:], strict=False):
        assert after <= 1.1 * before, errors


def judged(current_pct: float, candidate_pct: float, better: bool = False) -> Comparison:
    return Comparison(better, current_pct, candidate_pct, 400, 0.8, 'judged')


def test_could_be_better_says_by_how_much_and_what_to_do():
    calibration = Calibration(HARD_IRON_T, np.linalg.inv(SOFT_IRON), FIELD_T)
    findings = Findings()
    assert could_be_better(findings, calibration) is None  # nothing judged yet
    findings.headroom = (calibration, judged(2.0, 1.9))
    gain, text = could_be_better(findings, calibration)
    assert gain == pytest.approx(5.0)
    assert 'could be better by 5.0 %' in text and '~/calibrate' in text
    assert 'not yet beyond noise' in text
    findings.headroom = (calibration, judged(2.0, 2.1))
    gain, text = could_be_better(findings, calibration)
    assert gain == 0.0 and 'as good as a fit of the buffer' in text
    other = calibration.with_metadata(source='file')  # another calibration went in force
    assert could_be_better(findings, other) is None
    findings.headroom = (calibration, Comparison(False, float('nan'), float('nan'), 12, 0.0, ''))
    assert could_be_better(findings, calibration) is None  # too few readings said nothing


def test_diagnostics_report_the_headroom_of_the_calibration_in_force_until_it_changes():
    raw = recording(350, 6)
    rng = np.random.default_rng(6)
    session = CalibrationSession()
    index = 0
    for _ in range(4):
        index = feed(session, with_noise(raw, 0.02, rng), index)
    report = session.report(0.0, measure_coverage=True)
    values = report.values
    assert report.counts.fits.get('refine', 0) >= 2
    assert values['could_be_better_pct'] >= 0.0
    assert values['could_be_better']
    attempt = calibrate_now(session)
    assert attempt.success
    assert 'could_be_better_pct' not in session.report(0.0).values  # judged the old one


def test_a_fit_one_or_two_cells_narrower_may_replace_the_calibration_in_force():
    """Which of the 80 direction cells a buffer of 100 points reaches changes by a cell or two
    as points are replaced: a candidate better on held-out readings is not refused for that,
    but three cells fewer is a narrower buffer."""
    current = Calibration(HARD_IRON_T, np.linalg.inv(SOFT_IRON), FIELD_T, 'full',
                          {'coverage': 0.9})
    assert coverage_kept(current, current.with_metadata(coverage=0.9 - COVERAGE_SLACK))
    assert COVERAGE_SLACK == pytest.approx(2.0 / 80.0)
    assert not coverage_kept(current, current.with_metadata(coverage=0.9 - 3.0 / 80.0))
