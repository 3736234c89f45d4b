# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Fit jobs: one recipe per kind, the same outcome inline and in the worker process, errors
reported instead of raised, and a dead worker replaced."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.fitting import FitOptions
from mag_calibrator_ros.calibration.live import worker as fit_worker
from mag_calibrator_ros.calibration.live.jobs import REFERENCE_OPTIONS, FitJob, run_job
from mag_calibrator_ros.calibration.live.worker import InlineRunner, ProcessRunner
from mag_calibrator_ros.sim import motion

FIELD = 50.0
SOFT = np.array([[1.1, 0.05, 0.0], [0.05, 0.93, 0.02], [0.0, 0.02, 1.0]])
OFFSET = np.array([120.0, -40.0, 30.0])


def tumble(n=300, seed=0, noise=0.3):
    truth = motion.body_field_samples('tumble', n, 20.0, FIELD, 60.0, seed)
    raw = truth @ SOFT.T + OFFSET
    return raw + np.random.default_rng(seed).normal(0.0, noise, raw.shape)


def job(kind='calibrate', **changes):
    samples = tumble()
    values = dict(kind=kind, samples=samples, weights=np.ones(len(samples)), readings=samples,
                  options=REFERENCE_OPTIONS if kind == 'reference' else FitOptions(),
                  metadata={'units': 'uT', 'frame_id': 'imu_link'})
    values.update(changes)
    return FitJob(**values)


def wait(runner, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        outcome = runner.poll()
        if outcome is not None:
            return outcome
        time.sleep(0.01)
    raise AssertionError('the worker never answered')


def test_calibrate_fits_and_stamps_the_metadata():
    outcome = run_job(job())
    assert outcome.result.success and not outcome.error
    metadata = outcome.result.calibration.metadata
    assert metadata['units'] == 'uT' and metadata['frame_id'] == 'imu_link'
    assert metadata['time'].endswith('Z') and 'residual_rms_pct' in metadata
    assert outcome.reference is None and outcome.comparison is None


def test_an_automatic_attempt_fits_only_once_coverage_suffices():
    corner = tumble()[:20]  # the first 20 readings: a corner of the sphere
    outcome = run_job(job(samples=corner, weights=np.ones(20), readings=corner,
                          ready_coverage=0.5))
    assert outcome.result is None and not outcome.fitted
    assert outcome.coverage.fraction < 0.5
    assert run_job(job(ready_coverage=0.5)).fitted


def test_refine_compares_the_fit_with_the_calibration_in_force_on_the_evidence():
    evidence = tumble(400, seed=5)
    current = Calibration(OFFSET + [4.0, 0.0, 0.0], np.linalg.inv(SOFT), FIELD)
    outcome = run_job(job('refine', current=current, evidence=evidence))
    assert outcome.comparison is not None and outcome.comparison.better


def test_a_sane_reference_gets_a_tolerance_and_settles():
    first = run_job(job('reference'))
    reference = first.reference
    assert reference is not None and not reference.settled
    assert 0.0 < reference.tolerance <= 0.3
    again = run_job(job('reference', previous=reference.calibration))
    assert again.reference.settled


def test_an_undetermined_reference_is_not_sane():
    ring = motion.body_field_samples('yaw', 300, 20.0, FIELD, 60.0, 1) + OFFSET
    outcome = run_job(job('reference', samples=ring, weights=np.ones(300), readings=ring))
    assert outcome.reference is None


def test_a_job_that_raises_comes_back_as_an_error():
    outcome = run_job(job(weights=np.ones(3)))  # wrong length: fit_calibration says so...
    assert outcome.result is not None and not outcome.result.success
    broken = run_job(job(metadata={1: 'not a name'}))  # ...one that cannot run is an error
    assert broken.error and broken.result is None


def test_the_worker_process_gives_exactly_the_inline_outcome():
    runner = ProcessRunner()
    try:
        inline = InlineRunner()
        for kind in ('calibrate', 'reference'):
            inline.submit(job(kind))
            expected = inline.poll()
            runner.submit(job(kind))
            assert runner.busy
            got = wait(runner)
            assert not runner.busy and not got.error
            if kind == 'reference':
                expected, got = expected.reference, got.reference
            else:
                expected, got = expected.result, got.result
            np.testing.assert_array_equal(got.calibration.offset, expected.calibration.offset)
            np.testing.assert_array_equal(got.calibration.matrix, expected.calibration.matrix)
        with pytest.raises(RuntimeError):
            runner.submit(job())
            runner.submit(job())
        wait(runner)
    finally:
        runner.close()


def test_a_dead_worker_is_reported_and_replaced():
    runner = ProcessRunner()
    try:
        runner.submit(job())
        wait(runner)
        pid = runner.pid
        big = np.tile(tumble(), (67, 1))[:20000]  # long to fit; 300 tiled: quick to make
        runner.submit(job(samples=big, weights=np.ones(len(big))))
        os.kill(pid, signal.SIGKILL)
        outcome = wait(runner)
        assert outcome.error and 'worker' in outcome.error and runner.restarts == 1
        runner.submit(job())
        assert wait(runner).result.success  # a new worker took over
    finally:
        runner.close()


def test_the_outcome_carries_the_submitted_job_itself():
    """The session tells by identity whether a judged calibration is still in force: a copy
    that came back through the pipe would never be."""
    submitted = job('refine', current=Calibration(OFFSET, np.linalg.inv(SOFT), FIELD),
                    evidence=tumble(200, seed=6))
    for runner in (InlineRunner(), ProcessRunner()):
        try:
            runner.submit(submitted)
            outcome = wait(runner)
            assert outcome.job is submitted and outcome.job.current is submitted.current
        finally:
            runner.close()


@pytest.mark.skipif(not hasattr(os, 'sched_getscheduler'), reason='Linux scheduling policies')
def test_the_worker_yields_the_cpu_to_the_node():
    """The fit worker runs nicer than the node and as SCHED_BATCH, so a job written to it never
    preempts the node's message path; it still gets its share of a busy machine (not IDLE)."""
    runner = ProcessRunner()
    try:
        runner.submit(job())
        wait(runner)  # the worker is up and has set its priority before its first job
        assert os.sched_getscheduler(runner.pid) == os.SCHED_BATCH
        assert os.getpriority(os.PRIO_PROCESS, runner.pid) == min(
            os.getpriority(os.PRIO_PROCESS, 0) + fit_worker.WORKER_NICENESS, 19)
    finally:
        runner.close()


def test_a_worker_that_stops_answering_is_killed_restarted_and_said(monkeypatch):
    """A stopped (SIGSTOP) worker never answered: ~/calibrate waited for ever. The watchdog kills
    it after the deadline, the job comes back as an error naming why, a new worker takes over.
    The fits that must answer get a generous deadline; the one the stopped worker never answers
    a short one, so the test waits a second, not the generous deadline."""
    runner = ProcessRunner(deadline_s=60.0)
    ready = threading.Event()  # the new worker's 'ready' is read only once this is set
    try:
        runner.submit(job())
        assert wait(runner).result.success and runner.problem is None  # up and ready
        stopped, first_output = runner.pid, runner._worker.process.stdout
        real_receive = fit_worker.receive

        def receive(stream):
            # the new worker still starting, whatever the load: stopping it with SIGSTOP
            # "while it imports" lost that race on a loaded computer (it was up already)
            if stream is not first_output:
                ready.wait()
            return real_receive(stream)

        monkeypatch.setattr(fit_worker, 'receive', receive)
        os.kill(stopped, signal.SIGSTOP)
        runner.deadline_s = 1.0
        runner.submit(job())
        outcome = wait(runner)
        runner.deadline_s = 60.0
        assert outcome.error == ('the fit worker did not answer within 1 s: restarted; the next '
                                 'fit runs in the new worker')
        assert runner.restarts == 1 and runner.pid != stopped
        with pytest.raises(ProcessLookupError):  # killed and reaped
            os.kill(stopped, 0)
        assert runner.problem == ('the fit worker is restarting (restart 1: the fit worker did '
                                  'not answer within 1 s); fits wait until it is up')
        ready.set()
        runner.submit(job())
        assert wait(runner).result.success and runner.problem is None and runner.restarts == 1
    finally:
        ready.set()
        runner.close()



def test_an_idle_worker_that_is_stopped_is_said_and_replaced(monkeypatch):
    """Issue #47: a worker stopped (SIGSTOP) between fits left /diagnostics OK until a job had
    waited JOB_DEADLINE_S (300 s). Its state says it at once; after STOPPED_GRACE_S (1 s here)
    it is replaced without a job being lost, and the new one fits."""
    monkeypatch.setattr(fit_worker, 'STOPPED_GRACE_S', 1.0)
    runner = ProcessRunner()
    try:
        runner.submit(job())
        assert wait(runner).result.success and runner.problem is None
        stopped = runner.pid
        os.kill(stopped, signal.SIGSTOP)
        problems, deadline = set(), time.monotonic() + 60.0
        while runner.restarts == 0 and time.monotonic() < deadline:
            problems.add(runner.problem)
            assert runner.poll() is None  # no job: nothing comes back
            time.sleep(0.05)
        assert (f'the fit worker process {stopped} is stopped (SIGSTOP or a debugger): fits wait;'
                ' it is replaced after 1 s stopped') in problems
        assert runner.restarts == 1, problems
        assert runner.last_restart == 'the fit worker was stopped for more than 1 s'
        with pytest.raises(ProcessLookupError):  # killed and reaped
            os.kill(stopped, 0)
        runner.submit(job())
        assert wait(runner).result.success and runner.pid != stopped
    finally:
        runner.close()


def test_closing_the_runner_of_a_stopped_worker_ends_in_bounded_time():
    """Closing closed the worker's output before the worker had ended: that waited for the
    reader thread's read, which a stopped (SIGSTOP) worker never ends, and hung for ever (the
    test above failing on a loaded computer hung the whole suite so, issue #22)."""
    runner = ProcessRunner()
    try:
        runner.submit(job())
        assert wait(runner).result.success
        stopped = runner.pid
        os.kill(stopped, signal.SIGSTOP)
        started = time.monotonic()
    finally:
        runner.close()
    assert time.monotonic() - started < 30.0  # two seconds to end on end of input, then killed
    with pytest.raises(ProcessLookupError):  # killed and reaped
        os.kill(stopped, 0)

def test_a_worker_that_dies_between_fits_is_said_and_replaced_at_once():
    runner = ProcessRunner()
    try:
        runner.submit(job())
        wait(runner)
        os.kill(runner.pid, signal.SIGKILL)
        deadline = time.monotonic() + 30.0
        while runner.problem is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert runner.problem == ('the fit worker process ended (exit status -9); it is being '
                                  'restarted')
        assert runner.poll() is None and runner.restarts == 1
        assert runner.last_restart == 'the fit worker process ended (exit status -9)'
        runner.submit(job())
        assert wait(runner).result.success and runner.problem is None
    finally:
        runner.close()
