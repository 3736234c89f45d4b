# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""CalibrationSession without ROS: one call per message, every fit decided in one place and run
off the message path, reporting (refinement judged on held-out readings, a calibration that no
longer fits noticed, online tracking: test_session_refinement.py)."""

from __future__ import annotations

from dataclasses import replace
import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration, transform_covariance
from mag_calibrator_ros.calibration.live.backlog import DRAIN_FOR_REQUEST, DRAIN_PER_MESSAGE
from mag_calibrator_ros.calibration.live.evidence import HOLD_OUT_EVERY
from mag_calibrator_ros.calibration.live.jobs import FitJob, JobOutcome, run_job
from mag_calibrator_ros.calibration.live.offline import calibrate_now, feed
from mag_calibrator_ros.calibration.live.session import REFUSAL_REASONS, CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.live.worker import InlineRunner
from mag_calibrator_ros.nodes.mag_calibrator_parameters import AK09916_FULL_SCALE_T
from mag_calibrator_ros.sim import motion

FIELD_T = 50e-6
HARD_IRON_T = np.array([120e-6, -80e-6, 60e-6])
SOFT_IRON = np.array([[1.15, 0.10, -0.08], [0.10, 0.85, 0.12], [-0.08, 0.12, 1.00]])
EXACT = Calibration(HARD_IRON_T, np.linalg.inv(SOFT_IRON), FIELD_T, 'full',
                    {'residual_rms_pct': 0.6, 'coverage': 0.9})
RATE_HZ = 50.0


def truth_of(kind: str, n: int, seed: int = 0) -> np.ndarray:
    return motion.body_field_samples(kind, n, RATE_HZ, FIELD_T, 60.0, seed)


def distorted(kind: str, n: int, seed: int = 0, noise_t: float = 0.3e-6) -> np.ndarray:
    """Raw readings (T) of a board moving along ``kind``: S @ earth + h + noise."""
    truth = truth_of(kind, n, seed)
    rng = np.random.default_rng(seed)
    return truth @ SOFT_IRON.T + HARD_IRON_T + rng.normal(0.0, noise_t, truth.shape)


def direction_error_deg(calibration: Calibration, kind='tumble', n=500, seed=7) -> float:
    """RMS angle between the corrected and the true field over noise-free readings."""
    truth = truth_of(kind, n, seed)
    corrected = calibration.apply(truth @ SOFT_IRON.T + HARD_IRON_T)
    cosine = np.sum(corrected * truth, axis=1) / (
        np.linalg.norm(corrected, axis=1) * np.linalg.norm(truth, axis=1))
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cosine, -1, 1)) ** 2))))


def stream(session, samples, start_s=0.0, rate_hz=RATE_HZ):
    """Feed ``samples`` at ``rate_hz`` from ``start_s``; returns the session's events."""
    feed(session, samples, rate_hz, start_ns=round(start_s * 1e9), frame_id='imu_link')
    return session.take_events()


def counts_of(session):
    """What the session counted so far (messages, refusals, fits, adoptions ...)."""
    return session.report().counts


def progress(session):
    """The progress line with the coverage measured now."""
    return session.report(measure_coverage=True).progress


def messages(events, level=None, adopted=None):
    return [e.message for e in events
            if (level is None or e.level == level) and (adopted is None or e.adopted == adopted)]


class ManualRunner:
    """A worker that finishes a job only when told: shows what happens while a fit runs."""

    problem = None
    restarts = 0

    def __init__(self):
        self.job = None
        self.released = None
        self.submitted = []

    @property
    def busy(self):
        return self.job is not None

    def submit(self, job):
        assert self.job is None
        self.job = job
        self.submitted.append(job.kind)

    def release(self):
        self.released = run_job(self.job)

    def poll(self):
        outcome, self.released = self.released, None
        if outcome is not None:
            self.job = None
        return outcome

    def close(self):
        pass


class Recorded(InlineRunner):
    """Inline fits, each outcome kept: what the worker gave back to the session."""

    def __init__(self):
        super().__init__()
        self.outcomes = []

    def poll(self):
        outcome = super().poll()
        if outcome is not None:
            self.outcomes.append(outcome)
        return outcome


def settle(session, runner):
    """What the node's poll timer does once messages stop: every fit finishes (released) and
    every held reading is fed."""
    while runner.busy or counts_of(session).held:
        if runner.busy:
            runner.release()
        session.poll()


TRACKING = SessionSettings(online_tracking=True, refine=False, auto_calibrate=False,
                           tracking_max_change_rate=0.02)
"""Online tracking alone (test_session_refinement.py tracks with it too)."""


def other_robots_calibration():
    """robot2's file: another board, other iron."""
    return Calibration(HARD_IRON_T + np.array([140e-6, -60e-6, 20e-6]),
                       np.linalg.inv(SOFT_IRON.T @ SOFT_IRON) @ SOFT_IRON, FIELD_T, 'full',
                       {'residual_rms_pct': 0.5, 'coverage': 0.9})


# -- one call per message -------------------------------------------------------------------------


def test_every_refusal_is_counted_once_and_nothing_refused_is_corrected():
    session = CalibrationSession(SessionSettings(full_scale=AK09916_FULL_SCALE_T),
                                 calibration=EXACT)  # the node's limit: the engine has none
    good = (20e-6, 30e-6, -10e-6)
    assert session.process(100, 'imu_link', good).accepted
    cases = [(math.nan, 0.0, 1e-6), (0.0, 0.0, 0.0), (AK09916_FULL_SCALE_T, 0.0, 0.0),
             'garbage', (1.0, 2.0)]
    for field in cases:
        processed = session.process(200, 'imu_link', field)
        assert not processed.accepted and processed.corrected is None
    assert session.process(99, 'other', good).accepted is False
    counted = counts_of(session)
    counts = counted.rejects
    assert set(counts) == set(REFUSAL_REASONS)
    assert (counts['non_finite'], counts['zero'], counts['saturated']) == (3, 1, 1)
    assert counts['frame_changed'] == 1 and counted.accepted == 1


def test_corrected_output_uses_the_calibration_in_force():
    session = CalibrationSession(calibration=EXACT)
    raw = distorted('tumble', 5)
    for i, reading in enumerate(raw):
        processed = session.process(i * 10**7, 'imu_link', reading)
        np.testing.assert_allclose(processed.corrected, EXACT.apply(reading))
        assert processed.calibration is EXACT


def test_held_out_readings_never_enter_the_buffer():
    """Evidence is held out only while a calibration is in force (there is nothing to judge
    before), and what is held out never reaches the buffer."""
    uncalibrated = CalibrationSession(SessionSettings(auto_calibrate=False))
    stream(uncalibrated, distorted('tumble', 800))
    report = uncalibrated.report()
    assert report.buffer.seen == report.counts.accepted == 800
    assert report.counts.held_out == 0
    calibrated = CalibrationSession(SessionSettings(auto_calibrate=False), calibration=EXACT)
    stream(calibrated, distorted('tumble', 800))
    report = calibrated.report()
    held_out = 800 - report.buffer.seen
    assert 0.5 * 800 / HOLD_OUT_EVERY < held_out < 1.5 * 800 / HOLD_OUT_EVERY
    assert 0.8 * held_out <= report.counts.held_out <= held_out  # the latest few per cell


# -- calibrating by itself ------------------------------------------------------------------------


def test_calibrates_by_itself_and_corrects_strong_soft_iron():
    session = CalibrationSession()
    assert session.report().state == 'uncalibrated'
    events = stream(session, distorted('tumble', 3000))
    (first, *_) = messages(events, adopted=True)
    assert first.startswith('calibrated automatically: model')
    for word in ('offset', 'uT', 'residual', 'coverage', '%'):
        assert word in first
    assert session.report().state.startswith('calibrated')
    assert direction_error_deg(session.calibration) < 0.5
    metadata = session.calibration.metadata
    assert metadata['frame_id'] == 'imu_link' and metadata['units'] == 'T'


def test_readiness_is_checked_often_but_only_a_ready_buffer_is_fitted():
    session = CalibrationSession(SessionSettings(min_coverage=0.9))  # never ready in 3 s
    stream(session, distorted('tumble', 150))
    assert session.calibration is None
    assert counts_of(session).fits.get('calibrate', 0) > 5
    assert 'keep rotating' in progress(session)


def test_failing_automatic_fits_are_rate_limited_by_stream_time():
    settings = SessionSettings(auto_calibrate_period=5.0, max_residual_pct=0.01)
    session = CalibrationSession(settings)
    events = stream(session, distorted('tumble', 2500, noise_t=2e-6))  # 50 s of stream
    failures = messages(events, level='info')
    assert session.calibration is None
    assert 2 <= sum('not yet' in m for m in failures) <= 50.0 / 5.0 + 1


def test_auto_calibrate_off_never_fits_by_itself():
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    stream(session, distorted('tumble', 3000))
    assert session.calibration is None and 'calibrate' not in counts_of(session).fits
    assert 'call ~/calibrate' in progress(session)


def test_a_requested_calibration_is_answered_by_ticket_and_put_in_force():
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    stream(session, distorted('tumble', 3000))
    ticket = session.request_calibration()
    (answer,) = [e for e in session.take_events() if e.ticket == ticket]
    assert answer.attempt.success and answer.adopted and session.calibration is not None
    assert calibrate_now(session).success


def test_a_failed_request_keeps_the_previous_calibration_and_says_why():
    session = CalibrationSession(SessionSettings(model='full'), calibration=EXACT)
    session.reset()
    stream(session, distorted('still', 300, seed=2))
    attempt = calibrate_now(session)
    assert not attempt.success and 'previous calibration stays' in attempt.message
    assert len(attempt.message) > len('calibration failed: ; the previous calibration stays')
    assert session.calibration is EXACT


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_a_still_sensor_gives_the_buffer_no_reference_to_set_aside(seed):
    """A robot standing still at start-up: the buffer keeps the rim of its noise, whose own fit
    is no field sphere (the readings fill its inside). Taken as the reference it refused half the
    readings and was set aside with a log line, over and over."""
    session = CalibrationSession()
    events = stream(session, distorted('still', 3000, seed=seed))  # a minute at 50 Hz
    report = session.report()
    assert report.counts.fits['reference'] > 0
    assert report.buffer.screened_by is None
    assert not [m for m in messages(events) if 'stopped screening' in m]


def test_planar_data_with_a_3d_model_fails_uncalibrated():
    session = CalibrationSession(SessionSettings(model='full', auto_calibrate=False))
    stream(session, distorted('yaw', 2000))
    attempt = calibrate_now(session)
    assert not attempt.success and 'still uncalibrated' in attempt.message
    assert session.report().state == 'collecting'


# -- the buffer's reference -----------------------------------------------------------------------


def spiky(samples, share, seed):
    rng = np.random.default_rng(seed)
    spikes = rng.random(len(samples)) < share
    directions = rng.normal(size=(int(spikes.sum()), 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    out = samples.copy()
    out[spikes] += directions * rng.uniform(2.0, 5.0, (len(directions), 1)) * FIELD_T
    return out, spikes


def test_spikes_are_refused_and_evicted_with_no_calibration_given():
    """A uniqueness buffer loves spikes (73 of 100 points at 3 % on its own); the session gives
    it its own full fit as reference, which refuses and evicts them."""
    raw, spikes = spiky(distorted('tumble', 3000, seed=21), 0.03, seed=21)
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    stream(session, raw)
    report = session.report()
    assert report.counts.fits['reference'] >= 1 and report.buffer.merging
    spike_rows = set(map(tuple, raw[spikes]))
    # A point no reading merged into is the reading itself; readings merge only once a
    # reference is set, and setting it evicts the spikes it refuses.
    assert not {tuple(row) for row in session.view().raw} & spike_rows
    refused = report.counts.rejects['magnitude_outlier']
    assert 0.6 * spikes.sum() <= refused <= spikes.sum() + 5
    assert calibrate_now(session).success
    assert direction_error_deg(session.calibration) < 0.3
    view = session.view()  # and no point is a spike with readings merged in: all on the sphere
    assert np.all(np.abs(np.linalg.norm(view.corrected, axis=1) / view.field_strength - 1.0)
                  < 0.5)


def test_the_merged_buffer_fits_nearly_as_well_as_every_sample():
    """Each point carrying many readings: N = 100 points calibrate close to all 3,000 samples
    (random 100-sample subsets give about 0.2 deg here)."""
    session = CalibrationSession(SessionSettings(auto_calibrate=False, model='full'))
    stream(session, distorted('tumble', 3000, seed=25))
    assert session.report().buffer.merged > 1000
    assert calibrate_now(session).success
    assert direction_error_deg(session.calibration) < 0.12


def test_decisions_are_the_same_in_any_unit():
    raw, _ = spiky(distorted('tumble', 2000, seed=26), 0.02, seed=26)
    runs = []
    for scale in (1.0, 1e6, 1e6 / 0.15):  # tesla, microtesla, AK09916 counts
        settings = SessionSettings(full_scale=0.0, field_strength=0.0)
        session = CalibrationSession(settings, metadata={'units': 'x'})
        events = stream(session, raw * scale)
        runs.append((session, [e.message.split(':')[0] for e in events]))
    first, names = runs[0]
    for session, other_names in runs[1:]:
        assert other_names == names
        counts, first_counts = counts_of(session), counts_of(first)
        assert counts.fits == first_counts.fits and counts.adoptions == first_counts.adoptions
        np.testing.assert_array_equal(session.view().weights, first.view().weights)
        scale = session.calibration.field_strength / first.calibration.field_strength
        np.testing.assert_allclose(session.calibration.offset / scale,
                                   first.calibration.offset, rtol=1e-6, atol=1e-12)


def test_a_moved_sensor_sets_the_reference_aside_and_recalibrates():
    session = CalibrationSession()
    stream(session, distorted('tumble', 3000, seed=27))
    assert session.report().buffer.screened_by is not None
    moved = distorted('tumble', 3000, seed=28) + np.array([60e-6, 0.0, 0.0])  # 1.2 F off
    events = stream(session, moved, start_s=100.0)
    assert any('stopped screening' in m for m in messages(events))
    assert any('does not fit' in m for m in messages(events, level='warning'))
    assert any('recalibrated automatically' in m for m in messages(events, adopted=True))
    assert session.calibration.offset[0] == pytest.approx(HARD_IRON_T[0] + 60e-6, abs=1e-6)


def test_yaw_only_motion_merges_nothing():
    """Turning in place does not determine the full model the reference needs, so nothing is
    merged or placed on a surface a planar fit would misjudge."""
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    stream(session, distorted('yaw', 3000, seed=30))
    report = session.report()
    assert report.counts.fits['reference'] > 0
    assert not report.buffer.merging and report.buffer.merged == 0


# -- fits never run on the message path -----------------------------------------------------------


def test_while_a_fit_runs_readings_are_held_and_the_result_is_the_same():
    """The worker may take any time: readings wait and are fed in order afterwards, so the
    node (worker process) and mag_calibrator_fit (inline) agree on the same stream."""
    raw = distorted('tumble', 2500, seed=31)
    inline = CalibrationSession()
    stream(inline, raw)
    runner = ManualRunner()
    held = CalibrationSession(runner=runner)
    for i, reading in enumerate(raw):
        held.process(round(i * 1e9 / RATE_HZ), 'imu_link', reading)
        if runner.busy and i % 7 == 0:  # the worker answers a few messages later
            runner.release()
    settle(held, runner)
    assert runner.submitted and counts_of(held).fits == counts_of(inline).fits
    np.testing.assert_array_equal(held.view().raw, inline.view().raw)
    np.testing.assert_array_equal(held.calibration.offset, inline.calibration.offset)
    np.testing.assert_array_equal(held.calibration.matrix, inline.calibration.matrix)


def test_a_poll_feeds_a_few_held_readings_while_messages_flow_and_the_rest_once_they_stop():
    """The poll timer shares the node's thread with the messages: while they flow it feeds as
    few held readings as a message does, so none waits behind a long drain."""
    runner = ManualRunner()
    session = CalibrationSession(SessionSettings(auto_calibrate=False), runner=runner)
    stream(session, distorted('tumble', 300, seed=8))
    assert runner.busy and counts_of(session).held > DRAIN_PER_MESSAGE  # the reference fit
    runner.release()
    held = counts_of(session).held
    session.poll()
    assert held - counts_of(session).held == DRAIN_PER_MESSAGE
    session.poll()  # no message since the last poll: the stream stopped
    assert not counts_of(session).held or runner.busy  # all fed, unless a new fit became due


def test_a_poll_feeds_more_held_readings_while_a_request_waits_for_them():
    """~/calibrate fits every reading received before the call: while it waits for a slow
    worker's backlog, a poll feeds DRAIN_FOR_REQUEST instead of a message's few."""
    runner = ManualRunner()
    session = CalibrationSession(SessionSettings(auto_calibrate=False), runner=runner)
    stream(session, distorted('tumble', 300, seed=8))
    session.request_calibration()
    runner.release()
    held = counts_of(session).held
    assert held > DRAIN_FOR_REQUEST
    session.poll()
    assert held - counts_of(session).held == DRAIN_FOR_REQUEST


def test_a_request_made_while_readings_wait_fits_them_all():
    """~/calibrate fits the buffer with every reading received before the call, even those
    still held behind a running fit."""
    raw = distorted('tumble', 600, seed=32)
    inline = CalibrationSession(SessionSettings(auto_calibrate=False))
    stream(inline, raw)
    expected = calibrate_now(inline)
    runner = ManualRunner()
    held = CalibrationSession(SessionSettings(auto_calibrate=False), runner=runner)
    for i, reading in enumerate(raw):
        held.process(round(i * 1e9 / RATE_HZ), 'imu_link', reading)
    assert counts_of(held).held  # the buffer's reference fit (at 100 samples) still runs
    ticket = held.request_calibration()
    settle(held, runner)
    (answer,) = [e for e in held.take_events() if e.ticket == ticket]
    assert answer.attempt.success and expected.success
    np.testing.assert_array_equal(held.calibration.offset, inline.calibration.offset)


def test_a_reset_while_a_fit_runs_abandons_it_and_answers_the_request():
    runner = ManualRunner()
    session = CalibrationSession(SessionSettings(auto_calibrate=False), runner=runner)
    stream(session, distorted('tumble', 600))
    settle(session, runner)
    ticket = session.request_calibration()
    assert runner.busy
    session.reset()
    runner.release()
    session.poll()
    (answer,) = [e for e in session.take_events() if e.ticket == ticket]
    assert not answer.attempt.success and 'reset' in answer.message
    assert session.calibration is None and session.report().buffer.fill == 0


def test_a_worker_error_is_reported_and_the_session_carries_on():
    class Failing(ManualRunner):
        def release(self):
            self.released = JobOutcome(self.job, error='fit worker failed (boom)')

    runner = Failing()
    session = CalibrationSession(SessionSettings(auto_calibrate=False), runner=runner)
    feed(session, distorted('tumble', 300), RATE_HZ, frame_id='imu_link')
    ticket = session.request_calibration()
    settle(session, runner)  # the buffer's reference fit fails first, then the request
    events = session.take_events()
    (answer,) = [e for e in events if e.ticket == ticket]
    assert not answer.attempt.success and 'boom' in answer.message
    assert session.report().buffer.screened_by is None
    assert session.process(6 * 10**9, 'imu_link', (1e-5, 2e-5, 3e-5)).accepted


# -- reporting, settings --------------------------------------------------------------------------


class WatchedSession(CalibrationSession):
    """Notes what another thread would see at the moment the calibration in force changes: the
    counts right after the assignment that changed what ``calibration`` gives."""

    def __init__(self, *args, seen: list[int], **kwargs):
        self.counted_when_seen = seen
        super().__init__(*args, **kwargs)

    def __setattr__(self, name, value):
        before = getattr(self, 'calibration', None)  # None until the session has one
        super().__setattr__(name, value)
        if getattr(self, 'calibration', None) is not before:
            counts = self.report().counts
            self.counted_when_seen.append(sum(counts.adoptions.values())
                                          + counts.tracked_updates)


@pytest.mark.parametrize('settings', [SessionSettings(), TRACKING], ids=['refine', 'tracking'])
def test_a_calibration_is_in_force_only_once_it_is_counted(settings):
    """A thread polling the session (a test, a status page) must never see a calibration in
    force whose adoption is not yet counted or whose screening is not yet set up."""
    rough = Calibration(HARD_IRON_T + [4e-6, -2e-6, 0.0], 1.02 * EXACT.matrix, FIELD_T, 'full',
                        {'residual_rms_pct': 1.5, 'coverage': 0.5})
    seen: list[int] = []
    session = WatchedSession(settings, calibration=rough, seen=seen)
    stream(session, distorted('tumble', 3000, seed=40))
    assert len(seen) >= 2, seen  # given, then refined or tracked
    assert seen == list(range(1, len(seen) + 1))


def test_transform_covariance():
    matrix = np.array([[1.1, 0.1, 0.0], [0.1, 0.9, 0.0], [0.0, 0.0, 1.0]])
    assert not np.any(transform_covariance(matrix, np.zeros(9)))
    not_reported = np.zeros(9)
    not_reported[0] = -1.0
    np.testing.assert_array_equal(transform_covariance(matrix, not_reported), not_reported)
    covariance = np.diag([1.0, 2.0, 3.0])
    np.testing.assert_allclose(transform_covariance(matrix, covariance.reshape(9)),
                               (matrix @ covariance @ matrix.T).reshape(9))
    for bad in (math.nan, math.inf, 1e308):  # unknown, never NaN/Inf on the corrected topic
        broken = np.diag([1.0, bad, 3.0]).reshape(9)
        assert not np.any(transform_covariance(1e10 * matrix, broken))


def test_settings_validation_and_reconfigure_keep_samples():
    assert SessionSettings().problems() == []
    bad = SessionSettings(buffer_size=20, k=20, model='banana', min_coverage=2.0,
                          field_strength=-1.0, max_residual_pct=0.0, refine_period=0.0)
    assert len(bad.problems()) == 6
    with pytest.raises(ValueError, match='model'):
        CalibrationSession(replace(SessionSettings(), model='banana'))
    settings = SessionSettings(auto_calibrate=False)
    session = CalibrationSession(settings)
    stream(session, distorted('tumble', 1000))
    held = session.report().buffer.fill
    session.reconfigure(replace(settings, buffer_size=held + 40))
    buffer = session.report().buffer
    assert buffer.capacity == held + 40 and buffer.fill == held
    settings = replace(settings, buffer_size=held // 2)
    session.reconfigure(settings)
    assert session.report().buffer.fill == held // 2
    with pytest.raises(ValueError, match='k must'):
        session.reconfigure(replace(settings, k=held))


def test_reports_take_the_coverage_the_worker_measured_while_it_is_fresh():
    """Diagnostics read the coverage every second and measuring it costs milliseconds: reports
    take what the worker's latest check measured, and measure it themselves once that is stale
    (another stream second) or the buffer was emptied."""
    runner = Recorded()
    session = CalibrationSession(runner=runner)
    stream(session, distorted('tumble', 3000, seed=7))
    assert session.calibration is not None and counts_of(session).fits['check'] > 0
    (*_, worker) = [outcome.coverage for outcome in runner.outcomes
                    if outcome.coverage is not None]
    exact = session.report(measure_coverage=True).coverage
    reported = session.report().coverage
    assert reported is worker and reported.cells == exact.cells  # the worker's, not measured
    assert abs(reported.fraction - exact.fraction) <= 0.05
    session.reset()
    emptied = session.report().coverage
    assert emptied is not worker and emptied.fraction == 0.0  # measured here: nothing held


def test_diagnostic_values_are_plain_numbers_and_strings():
    session = CalibrationSession()
    session.report(0.0, measure_coverage=True)  # the first diagnostics period begins
    stream(session, distorted('tumble', 3000))
    session.process(10**12, 'imu_link', (0.0, 0.0, 0.0))
    report = session.report(2.0, measure_coverage=True)
    values = report.values
    assert values['state'].startswith('calibrated')
    assert values['input_rate_hz'] == pytest.approx(3001 / 2.0)
    assert values['rejected_zero'] == 1
    assert values['buffer_fill'] == report.buffer.fill
    for value in values.values():
        items = value if isinstance(value, list) else [value]
        assert all(type(item) in (int, float, str, bool) for item in items), value
    assert len(values['offset_uT']) == 3 and 'field_strength_uT' in values
    # what screening refused since the previous report is the message, once
    assert report.message == f'{report.state}: input messages refused since last report: zero 1'
    assert 'refused' not in session.report(3.0).message


def test_stream_changes_are_reported_and_followed():
    session = CalibrationSession(calibration=EXACT)
    raw = distorted('tumble', 20)
    feed(session, raw[:10], RATE_HZ, frame_id='imu_link')
    feed(session, raw[10:], RATE_HZ, start_ns=0, frame_id='imu_link')  # a bag starting over
    feed(session, raw, RATE_HZ, start_ns=10**9, frame_id='imu')  # the driver's frame_id changed
    events = session.take_events()
    assert any('jumped back' in m for m in messages(events, level='info'))
    assert any("to 'imu'" in m for m in messages(events, level='warning'))
    assert session.process(2 * 10**9, 'imu', raw[0]).corrected is not None


@pytest.mark.parametrize('inclination', [30.0, 70.0])
@pytest.mark.parametrize('model', ['planar', 'auto'])
def test_a_ground_robot_turning_with_floor_tilt_calibrates_at_high_latitude(model, inclination):
    """The floor tilts a turning robot 2-4°: at 70° inclination that changes the horizontal field
    by ~10 %, which a 2-D fit counted as a disturbed field; the planar fit explains it in 3-D."""
    truth = motion.body_field_samples('yaw', 3000, 50.0, FIELD_T, inclination, 3)
    raw = truth @ SOFT_IRON.T + HARD_IRON_T
    noisy = raw + np.random.default_rng(0).normal(0.0, 0.3e-6, truth.shape)
    session = CalibrationSession(SessionSettings(model=model, auto_calibrate=False))
    stream(session, noisy)
    attempt = calibrate_now(session)
    assert attempt.success, attempt.message
    metrics = attempt.outcome.result.metrics
    assert metrics.model == 'planar' and metrics.unobserved == ('matrix_normal',)
    assert metrics.residual_rms_pct < 2.0
    corrected = session.calibration.apply(raw)
    heading_error = np.degrees(np.angle(np.exp(1j * (
        np.arctan2(corrected[:, 1], corrected[:, 0]) - np.arctan2(truth[:, 1], truth[:, 0])
    ))))  # fmt: skip
    assert np.sqrt(np.mean(heading_error**2)) < 1.5


def test_a_job_made_by_the_session_is_a_complete_snapshot():
    runner = ManualRunner()
    session = CalibrationSession(SessionSettings(auto_calibrate=False), calibration=EXACT,
                                 runner=runner)
    stream(session, distorted('tumble', 500))
    settle(session, runner)
    assert 'refine' in runner.submitted
    ticket = session.request_calibration()
    job = runner.job  # a fit of the buffer as it is now, not run yet
    report = session.report()
    assert isinstance(job, FitJob) and job.ticket == ticket and job.current is EXACT
    assert len(job.samples) == len(job.weights) == report.buffer.fill
    assert len(job.evidence) == report.counts.held_out > 0
    job.samples[:] = 0.0  # a copy: the buffer is untouched
    assert np.all(session.view().raw != 0.0)


def test_with_the_worker_process_refinement_and_misfits_are_decided_too():
    """The node's own runner: outcomes judged against the calibration in force (regression: a
    job copied back through the pipe discarded every refinement and check)."""
    from mag_calibrator_ros.calibration.live.worker import ProcessRunner

    runner = ProcessRunner()
    try:
        session = CalibrationSession(calibration=other_robots_calibration(), runner=runner)
        for i, reading in enumerate(distorted('tumble', 3000, seed=43)):
            session.process(round(i * 1e9 / RATE_HZ), 'imu_link', reading)
        while runner.busy or counts_of(session).held:
            session.poll()
        events = session.take_events()
        assert any('does not fit' in m for m in messages(events, level='warning'))
        assert counts_of(session).adoptions.get('auto') == 1
        assert direction_error_deg(session.calibration) < 0.5
    finally:
        runner.close()


def test_a_stuck_fit_worker_answers_the_request_says_error_and_is_replaced():
    """A fit worker that stopped answering: ~/calibrate waited for ever, waiting_readings grew
    to its limit and /diagnostics stayed OK. The fits that must answer get a generous deadline;
    the one the stopped worker never answers a short one (the test waits a second)."""
    import os
    import signal
    import time

    from mag_calibrator_ros.calibration.live.worker import ProcessRunner

    runner = ProcessRunner(deadline_s=60.0)
    session = CalibrationSession(SessionSettings(auto_calibrate=False), runner=runner)

    def answer(ticket):
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            session.poll()
            for event in session.take_events():
                if event.ticket == ticket:
                    return event.attempt
            time.sleep(0.01)
        raise AssertionError('never answered')

    try:
        stream(session, distorted('tumble', 600, seed=9))
        while runner.busy or counts_of(session).held:
            session.poll()
        os.kill(runner.pid, signal.SIGSTOP)
        runner.deadline_s = 1.0
        attempt = answer(session.request_calibration())
        runner.deadline_s = 60.0
        assert not attempt.success
        assert attempt.message.startswith('calibration failed: the fit worker did not answer '
                                          'within 1 s: restarted; the next fit runs in the new '
                                          'worker')
        os.kill(runner.pid, signal.SIGSTOP)  # the new worker, caught while it imports
        report = session.report(1.0, measure_coverage=True)
        level, message = report.level, report.message
        assert level == 'ERROR' and message.startswith('the fit worker is restarting (restart 1')
        values = report.values
        assert values['fit_worker_restarts'] == 1
        assert values['fit_worker_last_restart'] == 'the fit worker did not answer within 1 s'
        os.kill(runner.pid, signal.SIGCONT)
        attempt = answer(session.request_calibration())
        assert attempt.success, attempt.message
        assert session.report().level == 'OK'
    finally:
        runner.close()


def test_a_calibration_whose_offset_is_beyond_the_full_scale_is_refused():
    """Issue #46 item 3: an offset no reading of this magnetometer can carry (beyond the
    configured full_scale: every reading would saturate) is another unit, refused where a
    calibration enters; without a full scale (0: a recording in an unknown unit) it is not
    judged."""
    beyond = Calibration(np.array([6e-3, 0.0, 0.0]), np.eye(3), 50e-6)
    session = CalibrationSession(SessionSettings(full_scale=AK09916_FULL_SCALE_T))
    problem = session.apply_calibration(beyond, 'file')
    assert problem is not None and 'beyond what the magnetometer reads (4.9128 mT full ' \
        'scale)' in problem, problem
    assert session.calibration is None
    within = Calibration(np.array([4e-3, 0.0, 0.0]), np.eye(3), 50e-6)
    assert session.apply_calibration(within, 'file') is None
    assert session.calibration is within
    assert CalibrationSession(SessionSettings()).apply_calibration(beyond, 'file') is None
