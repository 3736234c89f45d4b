# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""FitScheduler and StreamClock: when each fit runs, from the stream alone."""

from __future__ import annotations

from dataclasses import replace
import math

from mag_calibrator_ros.calibration.live.scheduler import (
    CHECK_FIT_PERIOD_S,
    CHECK_PERIOD_S,
    MAX_STEP_S,
    NOMINAL_STEP_S,
    REFERENCE_MAX_FACTOR,
    REFINE_FIRST_S,
    REFINE_MAX_FACTOR,
    FitScheduler,
    Situation,
    StreamClock,
)

IDLE = Situation(now=0.0, buffer_full=False, buffer_fill=0, calibrated=False, misfit=False,
                 auto_calibrate=True, auto_calibrate_period=2.0, refine=True, refine_period=10.0,
                 min_samples=30, request_waiting=False)


def test_stream_time_follows_stamps_with_bounded_steps():
    clock = StreamClock()
    assert clock.advance(5_000_000_000) == 0.0
    assert math.isclose(clock.advance(5_010_000_000), 0.01)
    assert math.isclose(clock.advance(9_000_000_000), 0.01 + MAX_STEP_S)  # a pause
    assert math.isclose(clock.advance(9_000_000_000), 0.01 + MAX_STEP_S + NOMINAL_STEP_S)
    assert math.isclose(clock.advance(1_000_000_000), 0.01 + MAX_STEP_S + 2 * NOMINAL_STEP_S)


def test_a_request_comes_first_then_the_reference():
    scheduler = FitScheduler(capacity=100)
    busy = replace(IDLE, buffer_full=True, buffer_fill=100, request_waiting=True)
    for _ in range(100):
        scheduler.sample_added(buffer_full=True)
    assert scheduler.due(busy) == 'request'
    assert scheduler.due(replace(busy, request_waiting=False)) == 'reference'


def test_the_reference_period_doubles_while_fits_settle():
    scheduler = FitScheduler(capacity=50)
    full = replace(IDLE, buffer_full=True, buffer_fill=50, auto_calibrate=False)
    periods = []
    for settled in (True, True, True, True, True, False):
        count = 0
        while scheduler.due(full) != 'reference':
            scheduler.sample_added(buffer_full=True)
            count += 1
        periods.append(count)
        scheduler.reference_done(settled)
    assert periods == [50, 100, 200, 400, 50 * REFERENCE_MAX_FACTOR, 50 * REFERENCE_MAX_FACTOR]
    scheduler.sample_added(buffer_full=False)  # filling up again does not count
    assert scheduler.due(full) is None


def test_automatic_attempts_check_often_and_fit_at_most_every_period():
    scheduler = FitScheduler(capacity=100)
    ready = replace(IDLE, buffer_fill=40)
    assert scheduler.due(replace(ready, buffer_fill=29)) is None  # too few samples
    assert scheduler.due(ready) == 'calibrate'
    scheduler.calibrate_done(0.0, fitted=False, auto_calibrate_period=2.0)  # not ready
    assert scheduler.due(replace(ready, now=CHECK_PERIOD_S / 2)) is None
    assert scheduler.due(replace(ready, now=CHECK_PERIOD_S)) == 'calibrate'
    scheduler.calibrate_done(CHECK_PERIOD_S, fitted=True, auto_calibrate_period=2.0)  # failed
    assert scheduler.due(replace(ready, now=2.0)) is None
    assert scheduler.due(replace(ready, now=2.0 + CHECK_PERIOD_S)) == 'calibrate'
    assert scheduler.due(replace(ready, auto_calibrate=False, now=100.0)) is None


def test_refinement_starts_soon_then_slows_to_its_period_and_further_once_converged():
    scheduler = FitScheduler(capacity=100)
    calibrated = replace(IDLE, calibrated=True, buffer_fill=100)
    times, now = [], 0.0
    while len(times) < 9:
        now = round(now + 0.25, 6)
        if scheduler.due(replace(calibrated, now=now)) == 'refine':
            times.append(now)
            judged = len(times) > 4  # the first few find too little held-out evidence
            scheduler.refine_done(judged=judged, adopted=False)
    gaps = [round(b - a, 6) for a, b in zip(times, times[1:], strict=False)]
    assert times[0] == 0.25 + REFINE_FIRST_S  # counted from the first reading calibrated
    assert gaps[:4] == [2.0, 4.0, 8.0, 10.0]  # doubling up to refine_period
    assert scheduler.converged
    assert 10.0 < gaps[-1] <= 10.0 * REFINE_MAX_FACTOR and gaps == sorted(gaps)
    scheduler.refine_done(judged=True, adopted=True)  # a new calibration: soon again
    assert not scheduler.converged
    assert scheduler.due(replace(calibrated, now=now + 0.5)) != 'refine'
    assert scheduler.due(replace(calibrated, now=now + 0.5 + REFINE_FIRST_S)) == 'refine'


def test_unjudged_refinements_do_not_count_towards_convergence():
    scheduler = FitScheduler(capacity=100)
    for _ in range(10):
        scheduler.refine_done(judged=False, adopted=False)
    assert scheduler.unimproved == 0 and not scheduler.converged


def test_a_misfit_switches_from_refining_to_calibrating():
    scheduler = FitScheduler(capacity=100)
    misfit = replace(IDLE, calibrated=True, misfit=True, buffer_fill=50, now=100.0)
    assert scheduler.due(misfit) == 'calibrate'
    assert scheduler.due(replace(misfit, auto_calibrate=False)) == 'check'  # still watched


def test_the_calibration_in_force_is_checked_every_stream_second():
    scheduler = FitScheduler(capacity=100)
    calibrated = replace(IDLE, calibrated=True, refine=False, buffer_fill=100)
    checks = [t / 10 for t in range(100)
              if scheduler.due(replace(calibrated, now=t / 10)) == 'check']
    assert checks == [float(t) * CHECK_FIT_PERIOD_S for t in range(10)]
    assert scheduler.due(replace(IDLE, now=100.0)) is None  # nothing to check uncalibrated
