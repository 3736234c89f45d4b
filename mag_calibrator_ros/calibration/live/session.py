"""The live calibrator between messages, kept apart from ROS so it can be tested without a graph.

A :class:`CalibrationSession` takes one call per message, ``process(stamp, frame, field)``, and
returns the corrected field; its comment block (above ``process``) follows one reading through
the rooms that decide about it: ``screening``, ``pairing``, ``buffer`` and ``evidence``,
``scheduler``, ``jobs`` and ``worker``, ``verdicts`` (whether a fit goes in force), ``tracker``
and ``report`` (every text and value for people). ``settings`` holds what a user can tune.

What it decided comes out as ``SessionEvent``s for the node to log and act on (auto-save,
service answers). Units are the caller's (tesla in the node); the engine is unit-free.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import math
import random
import time
from typing import NamedTuple

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import StaticAttitudes
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS, Coverage
from mag_calibrator_ros.calibration.fit.earth_field import EarthField, EarthReference
from mag_calibrator_ros.calibration.fit.heading import HeadingCoverage, PlaneWatch
from mag_calibrator_ros.calibration.live import report
from mag_calibrator_ros.calibration.live.alignment_wait import AlignmentWait
from mag_calibrator_ros.calibration.live.backlog import DRAIN_PER_MESSAGE, Backlog
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.compensation import CompensationLearner
from mag_calibrator_ros.calibration.live.evidence import (
    HOLD_OUT_EVERY,
    MISFIT_WINDOW_S,
    HeldOutEvidence,
    MisfitMonitor,
)
from mag_calibrator_ros.calibration.live.findings import Findings
from mag_calibrator_ros.calibration.live.hints import MotionHints
from mag_calibrator_ros.calibration.live.jobs import REFERENCE_OPTIONS, FitJob, JobOutcome
from mag_calibrator_ros.calibration.live.pairing import ImuPairing, Pair, RateMeter
from mag_calibrator_ros.calibration.live.reference import BufferReference
from mag_calibrator_ros.calibration.live.report import CalibrationAttempt
from mag_calibrator_ros.calibration.live.sanity import InputWatch
from mag_calibrator_ros.calibration.live.scheduler import (
    CHECK_FIT_PERIOD_S,
    FitScheduler,
    Situation,
    StreamClock,
)
from mag_calibrator_ros.calibration.live.screening import SCREEN_REASONS, ReadingScreen
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.live.tracker import OnlineTracker, new_direction
from mag_calibrator_ros.calibration.live.verdicts import (
    Verdict,
    automatic_verdict,
    check_verdict,
    judged_on_evidence,
    passed_own_gates,
    realign_verdict,
    refinement_verdict,
    request_verdict,
)
from mag_calibrator_ros.calibration.live.view import CalibrationView, calibration_view
from mag_calibrator_ros.calibration.live.worker import FitRunner, InlineRunner

REFUSAL_REASONS = (*SCREEN_REASONS, 'duplicate', 'magnitude_outlier')
"""Every reason a reading is not used: screening, then the buffer's own two."""

STATES = ('uncalibrated', 'collecting', 'calibrated', 'calibrated-refining',
          'calibrated-converged', 'calibrated-misfit')

REPORTED_COVERAGE_AGE_S = 2.0 * CHECK_FIT_PERIOD_S
"""Stream seconds a coverage measured by the fit worker stands for the buffer's in reports: a
check measures it every CHECK_FIT_PERIOD_S while calibrated, a readiness test every
CHECK_PERIOD_S while calibrating automatically."""

PERIODIC_S = 1.0
"""Stream seconds between updates of the field's centre (for filing evidence by direction)."""

MAX_EVENTS = 1000


class Processed(NamedTuple):
    """What ``process`` made of one message."""

    accepted: bool
    corrected: np.ndarray | None
    """The corrected field, None while uncalibrated (or when refused)."""
    calibration: Calibration | None
    """The calibration that corrected it (for the covariance)."""
    uncertainty: float = 0.0
    """While the calibration in force is judged not to fit (calibrated-misfit), the median |B|
    error measured (``MisfitMonitor.uncertainty``): the node marks the message with it."""


_REFUSED = Processed(False, None, None)


@dataclass(frozen=True)
class SessionEvent:
    """Something the session decided, for the log (``level``: 'info', 'warning' or 'debug').

    ``adopted``: a new calibration is in force (auto_save applies); ``ticket``: the answer to
    ``request_calibration``.
    """

    level: str
    message: str
    adopted: bool = False
    ticket: int | None = None
    attempt: CalibrationAttempt | None = None


class CalibrationSession:
    """The calibrator's state between messages: buffer, evidence, calibration in force, fits."""

    def __init__(
        self,
        settings: SessionSettings | None = None,
        calibration: Calibration | None = None,
        runner: FitRunner | None = None,
        metadata: Mapping[str, object] | None = None,
    ) -> None:
        self.settings = settings or SessionSettings()
        problems = self.settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        self.runner = runner or InlineRunner()
        self.metadata = {'units': 'T', **(metadata or {})}
        """Stamped on every fitted calibration (units, source ...)."""
        self.units = str(self.metadata['units'])
        self.buffer = SampleBuffer(self.settings.buffer_size, self.settings.k)
        self.screen = ReadingScreen(self.settings.full_scale_limit)
        self.evidence = HeldOutEvidence()
        self.scheduler = FitScheduler(self.settings.buffer_size)
        self.misfit = MisfitMonitor()
        self.clock = StreamClock()
        self.refusals = dict.fromkeys(REFUSAL_REASONS[len(SCREEN_REASONS):], 0)
        self.accepted = 0
        self._accepted_at_poll = 0  # accepted messages at the previous poll(): is the stream idle?
        self.input_rate = RateMeter()
        self.calibration: Calibration | None = None
        """The calibration in force; only ``_put_in_force`` changes it."""
        self.last_attempt: CalibrationAttempt | None = None
        self.adoptions: dict[str, int] = {}
        """How often a calibration went in force, by source (auto, refine, request, file ...)."""
        self.jobs_run: dict[str, int] = {}
        self.stale_dropped = 0
        """Readings dropped unlearnt: compensated by a compensation no longer in force."""
        self.tracker: OnlineTracker | None = None
        self.tracked_updates = 0
        self._last_taught: np.ndarray | None = None  # corrected direction last fed to the tracker
        self._last_tracking_check: float | None = None
        self.buffer_reference = BufferReference(self.buffer)
        self.backlog = Backlog()  # (reading, stamp, epochs, state, pair) while a fit runs
        self._compensation_epoch = 0  # bumped by each compensation put in force
        self._state_specs: tuple | None = None  # the own-field inputs the states are made of
        self._state_epoch = 0  # bumped when they change: states made before mean nothing
        self._job: FitJob | None = None
        self._job_epoch = (0, 0)  # (_epoch, _compensation_epoch) when the job was made
        self._measured_coverage: tuple[float, Coverage] | None = None  # (stream s, coverage)
        self._epoch = 0  # bumped by reset(): outcomes of older jobs are stale
        self._next_ticket = 1
        self._hold_out = random.Random(0)
        self._next_periodic = 0.0
        self._events: deque[SessionEvent] = deque(maxlen=MAX_EVENTS)
        self._reported_rejects = dict(self.screen.counts)
        self.hints = MotionHints()  # the kind of hint, judged at stream points (hints.py)
        self.input_watch = InputWatch(self.units == 'T')  # wrong units, normalised input
        self.alignment_wait = AlignmentWait()  # the first calibration waits to be aligned
        self.attitudes = StaticAttitudes()
        """Quasi-static (field, accel) attitudes paired from the IMU, for the alignment."""
        self.pairing = ImuPairing()
        self.findings = Findings()
        """The model's field here, the latest alignment and model check (``findings.py``)."""
        self.compensation = CompensationLearner(*self.settings.compensation)  # K u + c (T - T0)
        if calibration is not None:
            self.apply_calibration(calibration, 'given')

    # -- configuration -------------------------------------------------------------------------

    def reconfigure(self, settings: SessionSettings) -> None:
        """Adopt new settings; a resized buffer keeps its most unique samples."""
        problems = settings.problems()
        if problems:
            raise ValueError('; '.join(problems))
        old, self.settings = self.settings, settings
        if (settings.buffer_size, settings.k) != (old.buffer_size, old.k):
            self.buffer.resize(settings.buffer_size, settings.k)
            self.scheduler.capacity = settings.buffer_size
        self._measured_coverage = None  # measured with the old settings (model, buffer)
        self.screen.full_scale = settings.full_scale_limit
        if settings.online_tracking != old.online_tracking:
            self._restart_tracker()
        self.compensation.configure(*settings.compensation)

    def close(self) -> None:
        """Stop the fit worker (the node calls this on shutdown)."""
        self.runner.close()

    # -- per message ---------------------------------------------------------------------------
    # The path of one reading, a call of ``process``:
    # 1. screen:   screening.ReadingScreen refuses what no fit should see (non-finite, zero,
    #              saturated, out of range, stamps going back or jumping, another frame).
    # 2. pair:     pairing.ImuPairing gives it the accelerometer sample taken with it, when an
    #              IMU feeds ``process_imu``.
    # 3. learn:    ``_ingest``: a held-out share goes to evidence.HeldOutEvidence (to judge
    #              calibrations on), the rest to buffer.SampleBuffer (screened by
    #              reference.BufferReference) and the tracker, a paired still one to
    #              alignment.StaticAttitudes. While a fit runs, readings wait in
    #              ``_hold`` and are fed afterwards in order (``_advance``), so the result does not
    #              depend on how long the fit took.
    # 4. correct:  the calibration in force (``Calibration.apply``) corrects it.
    # 5. publish:  ``Processed`` goes back to the caller: the node publishes it (with
    #              ``transform_covariance``), ``mag_calibrator_fit`` reports on the run.
    # 6. schedule: scheduler.FitScheduler says which fit is due (``_ingest``); ``_submit`` makes
    #              its jobs.FitJob for the worker.FitRunner; its outcome comes back to
    #              ``_complete``, which asks verdicts.py whether it goes in force
    #              (``_put_in_force``).

    def process(self, stamp_ns: int, frame_id: str, field: Sequence[float]) -> Processed:
        """Screen one message, learn from it, and correct it with the calibration in force."""
        self.input_rate.count += 1
        try:
            x0, x1, x2 = (float(value) for value in field)
        except (TypeError, ValueError):
            x0 = x1 = x2 = math.nan
        for problem in self.input_watch.offer(stamp_ns, (x0, x1, x2)):  # each said once
            self._event('warning', problem)
        reason = self.screen.screen(stamp_ns, frame_id, x0, x1, x2)
        if self.screen.changes:
            for change in self.screen.take_changes():
                self._event('warning' if change.kind == 'frame' else 'info', change.message)
        if reason is not None:
            return _REFUSED
        self.accepted += 1
        self._sync_states()
        reading, state = self.compensation.observe(stamp_ns, np.array((x0, x1, x2)),
                                                   self.calibration)
        epochs = (self._compensation_epoch, self._state_epoch)
        decided = self.pairing.settle(stamp_ns, frame_id, (reading, stamp_ns, epochs, state))
        if self.pairing.has_warnings:
            self._imu_warnings()
        self._advance()
        for item, pair in decided:  # arrival order, each once its IMU sample could be there
            (self._hold if self._job is not None or len(self.backlog) else self._ingest)(
                *item, pair)
        calibration = self.calibration
        if calibration is None:
            return Processed(True, None, None)
        return Processed(True, calibration.apply(reading), calibration, self.misfit.uncertainty)

    def process_imu(self, stamp_ns: int, frame_id: str, accel: Sequence[float],
                    gyro: Sequence[float] | None = None) -> bool:
        """Keep one accelerometer (m/s^2) and gyroscope (rad/s) sample to pair magnetometer
        readings with (``ImuPairing.add``); False when refused, counted by reason: no plausible
        specific force, or ``frame_id`` not the magnetometer stream's (said once a frame)."""
        self.input_watch.offer_imu(accel)
        kept = self.pairing.add(stamp_ns, accel, gyro, frame_id, self.screen.frame_id)
        if kept and gyro is not None and self.compensation.learning:
            self.compensation.gyro(stamp_ns, gyro)
        if self.pairing.has_warnings:
            self._imu_warnings()
        return kept

    def _imu_warnings(self) -> None:
        for warning in self.pairing.take_warnings():
            self._event('warning', warning)

    def set_earth_field(self, field: EarthField | None) -> None:
        """The World Magnetic Model's field here (None: unknown); used by the next fits."""
        self.findings.earth = field

    def poll(self) -> None:
        """Take a finished fit's outcome and feed held readings (``Backlog.budget``: a few while
        messages flow, more while a request waits, all once none came since the last poll);
        the node calls this on a timer (messages call it too), so answers arrive even when no
        message does."""
        flowing = self.accepted != self._accepted_at_poll
        self._accepted_at_poll = self.accepted
        self._advance(budget=self.backlog.budget(flowing))

    def _advance(self, budget: int = DRAIN_PER_MESSAGE) -> None:
        if self._job is not None:
            outcome = self.runner.poll()
            if outcome is None:
                return
            self._job = None
            self._complete(outcome)
        while len(self.backlog) and self._job is None and budget > 0:
            self._ingest(*self.backlog.next())
            budget -= 1
        if self._job is None and not len(self.backlog) and self.backlog.waiting:
            self._submit('request')

    def _hold(self, reading: np.ndarray, stamp_ns: int, epochs: tuple[int, int],
              state: tuple[float, ...], pair: Pair | None = None) -> None:
        overflow = self.backlog.hold((reading, stamp_ns, epochs, state, pair))
        if overflow is not None:  # the backlog is full: its oldest is fed now
            self._ingest(*overflow)

    def _ingest(self, reading: np.ndarray, stamp_ns: int, epochs: tuple[int, int],
                state: tuple[float, ...] | None, pair: Pair | None = None) -> None:
        """Everything a reading teaches, in stream order (the held ones after the fit).

        ``epochs``: the compensation the reading was compensated by on arrival, and the inputs
        its own-field ``state`` is made of (``CompensationLearner.observe``). A compensation put
        in force since moved the buffer and evidence (``_put_in_force``); a reading that was
        held (a fit ran) or waited for its IMU sample then still carries the old one's
        correction and teaches nothing: how many there are depends on how long the fit took,
        and on a loaded computer a backlog of them, some not compensated at all, went into the
        buffer and failed the next fit (a residual of 5.9 %, issue #22). A state of other
        inputs than today's is unknown."""
        now = self.clock.advance(stamp_ns)
        self.backlog.ingested += 1
        if epochs[0] != self._compensation_epoch:
            self.stale_dropped += 1
            return
        if epochs[1] != self._state_epoch:
            state = None
        if pair is not None and self.settings.align:
            self.attitudes.add(now, reading, pair[0], pair[1])
        # Evidence judges a calibration: none yet, none needed. The draw is pseudo-random (and
        # deterministic), so a recording replayed again holds out other readings.
        if self.calibration is not None and self._hold_out.random() * HOLD_OUT_EVERY < 1.0:
            self.evidence.add(reading, self.buffer_reference.direction(reading), now, state)
        else:
            if self.buffer_reference.left_plane(reading):
                self._leave_plane()
            outcome = self.buffer.add(reading, None if pair is None else pair[2], state)
            if outcome in self.refusals:
                self.refusals[outcome] += 1
            else:
                self.scheduler.sample_added(self.buffer.fill == self.buffer.capacity)
            if self.buffer_reference.source is not None:
                self._check_reference()
            if self.tracker is not None:
                direction = new_direction(self.calibration.apply(reading), self._last_taught)
                if direction is not None:
                    self._last_taught = direction
                    self.tracker.update(reading)
        if now >= self._next_periodic:
            self._next_periodic = now + PERIODIC_S
            self._update_centre()
            self._answer(self.compensation.window_answer(now, self.calibration))
        self.hints.learnt(now, self.buffer, reading)  # the kind of hint (hints.py)
        if self._job is None:
            kind = (self.scheduler.due(self._situation(now))
                    or self.compensation.due(now, self.calibration))  # 'compensate' or None
            if kind is not None:
                self._submit(kind)

    def _update_centre(self) -> None:
        radius = 0.0
        if self.calibration is not None:
            radius = self.calibration.field_radius()
        elif self.buffer.fill >= 10:
            radius = self.buffer.field_radius()
        self.attitudes.field_scale = radius if radius > 0.0 else None
        self.buffer_reference.update_centre()

    def _situation(self, now: float) -> Situation:
        return Situation.of(now, self.settings, self.buffer.fill, self.buffer.capacity,
                            self.calibration is not None, self.misfit.misfit,
                            self.backlog.request_ready)

    # -- fits ----------------------------------------------------------------------------------

    def _submit(self, kind: str) -> None:
        ticket = self.backlog.take_request() if kind == 'request' else None
        if self.input_watch.refusal(kind):  # wrong units or normalised: nothing to put in force
            return self._refuse_fit(kind, ticket, self.input_watch.problem)
        job = self._make_job(kind, ticket)
        self.jobs_run[job.kind] = self.jobs_run.get(job.kind, 0) + 1
        self._job, self._job_epoch = job, (self._epoch, self._compensation_epoch)
        self.runner.submit(job)
        outcome = self.runner.poll()  # an inline runner has it already
        if outcome is not None:
            self._job = None
            self._complete(outcome)

    def _refuse_fit(self, kind: str, ticket: int | None, problem: str) -> None:
        now, period = self.clock.now, self.settings.auto_calibrate_period
        if kind == 'calibrate':  # tried again a period later: the input may be fixed by then
            self.scheduler.calibrate_done(now, True, period)
        if ticket is not None:
            attempt = CalibrationAttempt(False, f'calibration refused: {problem}')
            self._event('warning', attempt.message, ticket=ticket, attempt=attempt)

    def _make_job(self, kind: str, ticket: int | None) -> FitJob:
        buffer = self.buffer
        samples, weights, readings = buffer.samples, buffer.counts, buffer.readings
        if kind == 'compensate':  # the robot's own field: live/compensation.py
            return self.compensation.job(self.calibration)
        if kind == 'reference':
            return FitJob('reference', samples, weights, readings, REFERENCE_OPTIONS,
                          previous=self.buffer_reference.provisional)
        if kind == 'check':
            recent = self.evidence.readings(since_s=self.clock.now - MISFIT_WINDOW_S)
            plane = self.buffer_reference.calibration_plane
            if plane is not None:  # a planar one knows nothing off its plane
                recent = recent[plane.near(recent)]
            tracked = None if self.tracker is None else self.tracker.calibration
            return FitJob('check', samples, weights, readings, self.settings.fit_options(),
                          current=self.calibration, evidence=self.evidence.readings(),
                          recent=recent, tracked=tracked, reference=buffer.reference)
        metadata = {**self.metadata, 'frame_id': self.frame_id}
        evidence = self.evidence.readings() if self.calibration is not None else None
        attitudes = self.attitudes.snapshot() if self.settings.align else None
        return FitJob(
            'refine' if kind == 'refine' else 'calibrate', samples, weights, readings,
            self.findings.fit_options(self.settings, self.units), metadata=metadata,
            current=self.calibration,
            evidence=evidence, ticket=ticket,
            ready_coverage=self.settings.min_coverage if kind == 'calibrate' else None,
            reference=buffer.reference,
            attitudes=attitudes if attitudes is not None and (len(attitudes)
                                                              or self.pairing.paired)
            else None,
            alignment=self.settings.alignment_options(self.findings.earth),
            earth=self.earth_reference(),
            ups=buffer.ups if buffer.paired else None,
            paired=buffer.paired_readings if buffer.paired else None,
        )

    def earth_reference(self) -> EarthReference | None:
        """The World Magnetic Model's field here with the tolerances a fit is checked by."""
        return self.findings.earth_reference(self.settings, self.units)

    # -- a fit's outcome -----------------------------------------------------------------------

    def _stale(self, job: FitJob) -> str | None:
        """Why a finished job's outcome no longer describes the session, None when it does."""
        reset, compensated = self._job_epoch
        if reset != self._epoch:
            return 'the buffer was reset while it ran'
        if compensated != self._compensation_epoch and job.kind != 'compensate':
            return ("another compensation of the robot's own field went in force while it ran "
                    '(it fitted readings since moved): ask again')
        return None

    def _complete(self, outcome: JobOutcome) -> None:
        """A finished fit: the verdict of its kind (verdicts.py) applied, with the bookkeeping
        around it (the scheduler, the latest alignment and model check)."""
        job = outcome.job
        stale = self._stale(job)
        if stale is not None:
            if job.ticket is not None:
                attempt = CalibrationAttempt(False, f'calibration abandoned: {stale}', outcome)
                self._event('warning', attempt.message, ticket=job.ticket, attempt=attempt)
            return
        if outcome.coverage is not None:
            self._measured_coverage = (self.clock.now, outcome.coverage)
        current = self.calibration
        if job.kind == 'reference':
            self._reference_done(outcome)
        elif job.kind == 'check':
            self._check_done(outcome)
        elif job.kind == 'compensate':
            verdict = self.compensation.judged(outcome, current)
            self._apply(verdict)
            self._answer(self.compensation.window_answer(self.clock.now, self.calibration,
                                                         verdict))
        elif job.ticket is not None:
            self._note_reference(outcome)
            verdict = request_verdict(outcome, current, self.units, self.findings.earth)
            self._apply(verdict, job.ticket)
        elif job.kind == 'calibrate':
            self.scheduler.calibrate_done(self.clock.now, outcome.fitted or bool(outcome.error),
                                          self.settings.auto_calibrate_period)
            if outcome.result is not None and not outcome.error:
                self._note_reference(outcome)
            self._apply(self.alignment_wait.judge(
                automatic_verdict(outcome, current, self.misfit.misfit, self.units,
                                  self.findings.earth),
                outcome, self.clock.now, self.pairing.paired > 0, self.settings.align))
        else:
            verdict = refinement_verdict(outcome, current)
            self._apply(verdict)
            if not outcome.error:
                self._note_reference(outcome)
            if verdict.adopt is None:
                self._apply(realign_verdict(outcome, current))
            self.scheduler.refine_done(judged_on_evidence(outcome.comparison),
                                       verdict.adopt is not None)

    def _apply(self, verdict: Verdict, ticket: int | None = None) -> None:
        """Record a verdict's attempt, put its calibration in force and log it. The event
        carries the attempt when it answers a request or puts the fit in force."""
        if verdict.attempt is not None:
            self.last_attempt = verdict.attempt
        adopted = verdict.adopt is not None
        if adopted:
            self._put_in_force(verdict.adopt, verdict.source)
        if verdict.message:
            carried = verdict.attempt if ticket is not None or adopted else None
            self._event(verdict.level, verdict.message, adopted=adopted, ticket=ticket,
                        attempt=carried)

    def _reference_done(self, outcome: JobOutcome) -> None:
        fit = outcome.reference
        self.scheduler.reference_done(fit is not None and fit.settled)
        if fit is None:
            return
        self.buffer_reference.provisional = fit.calibration
        self.buffer_reference.set(fit.calibration, fit.tolerance, 'fit')

    def _check_done(self, outcome: JobOutcome) -> None:
        """The calibration in force judged on recent evidence: misfit, and online tracking."""
        now = self.clock.now
        misfit_change = since_last_check_s = None
        if not outcome.error and outcome.job.current is self.calibration:
            misfit_change = self.misfit.update(now, outcome.fit_check)
            if outcome.comparison is not None:
                last, self._last_tracking_check = self._last_tracking_check, now
                since_last_check_s = None if last is None else now - last
        verdict = check_verdict(outcome, self.calibration, misfit_change, since_last_check_s,
                                self.settings, self.units)
        if verdict.message:
            self._event(verdict.level, verdict.message)
        if verdict.collect_anew:
            self._collect_anew(now)
        if verdict.adopt is not None:
            self._put_in_force(verdict.adopt, verdict.source)

    def _note_reference(self, outcome: JobOutcome) -> None:
        """Only a fit that passed its own gates (the model's aside) tells about the place."""
        for warning in self.findings.note(outcome) if passed_own_gates(outcome) else ():
            self._event('warning', warning)

    def alignment_warning(self) -> str:
        """A mounting error the latest alignment found, for a diagnostics WARN ('' if none)."""
        return self.findings.alignment_warning

    def earth_warning(self) -> str:
        """The calibration in force against the model, for a diagnostics WARN ('' if fine)."""
        return self.findings.earth_warning(self.calibration, self.settings, self.units)

    def request_calibration(self) -> int:
        """Ask for a fit of the buffer (``~/calibrate``) once every reading received so far is
        in it (some may wait while another fit runs); the answer comes as an event with this
        ticket. A fit that passes the gates goes in force."""
        ticket = self._next_ticket
        self._next_ticket += 1
        self.backlog.request(ticket, self.accepted)  # after every reading received so far
        for item, pair in self.pairing.flush():  # those waiting for an IMU sample decided now
            self._hold(*item, pair)
        self._advance()
        return ticket

    def calibrate_now(self, timeout_s: float = 60.0) -> CalibrationAttempt:
        """Request a fit and wait for it (offline use: ``mag_calibrator_fit``, tests)."""
        ticket = self.request_calibration()
        deadline = time.monotonic() + timeout_s
        while True:
            for event in self._events:
                if event.ticket == ticket and event.attempt is not None:
                    return event.attempt
            if time.monotonic() > deadline:
                return CalibrationAttempt(False, f'calibration did not finish in {timeout_s} s')
            time.sleep(0.001)
            self.poll()

    def request_compensation(self, timeout_s: float) -> int:
        """Learn the robot's own field now (``~/learn_compensation``): fits every few seconds
        of stream while its motors run through several currents, until one goes in force or
        ``timeout_s`` of stream pass (``CompensationLearner.open_window``); the answer comes
        as an event with this ticket."""
        ticket = self._next_ticket
        self._next_ticket += 1
        problem = self.compensation.open_window(ticket, self.clock.now, timeout_s,
                                                self.calibration, self.units)
        if problem:
            self._answer((ticket, CalibrationAttempt(False, problem)))
        return ticket

    def end_compensation_window(self, reason: str) -> None:
        """Answer an open ``request_compensation`` now with ``reason`` (the node's own deadline:
        stream time stands still while no reading comes)."""
        self._answer(self.compensation.close_window(reason))

    def _answer(self, answer: tuple[int, CalibrationAttempt] | None) -> None:
        if answer is not None:  # a success was logged when its compensation went in force
            ticket, attempt = answer
            self._event('debug' if attempt.success else 'warning', attempt.message,
                        ticket=ticket, attempt=attempt)

    # -- the calibration in force and the buffer's reference -----------------------------------

    def apply_calibration(self, calibration: Calibration, source: str = 'file') -> None:
        """Put a calibration in force at once (a file, parameters)."""
        self._put_in_force(calibration, source)

    def _put_in_force(self, calibration: Calibration, source: str) -> None:
        """The one door through which the calibration in force changes; ``source`` says why.

        A new calibration ('given', 'file', 'parameters', 'request', 'auto', 'refine') is counted
        in ``adoptions`` and judged afresh: the misfit monitor, the scheduler and the tracker
        restart, and it screens the buffer unless the buffer has a fit of its own. 'realign'
        rotates the one in force into the IMU frame (only the tracker restarts); 'tracking'
        steps it towards the tracker's (counted in ``tracked_updates``; the buffer's reference
        follows when it is the calibration in force; a static fit keeps the compensation)."""
        calibration = self.compensation.carry(calibration, self.calibration, source)
        self._sync_states()
        reference = self.buffer_reference
        if source == 'tracking':
            self.tracked_updates += 1
            if reference.source == 'calibration':
                reference.set(calibration, None, 'calibration')
            self.calibration = calibration
            return
        if source != 'realign':
            new = calibration.compensation
            in_force = None if self.calibration is None else self.calibration.compensation
            moved = not (new is in_force or (new is not None and new.same_field(in_force)))
            if moved:  # learned, or a file's
                self._recompensate(calibration)
            reference.calibration_plane = None
            if calibration.model == 'planar':
                reference.calibration_plane = PlaneWatch.of(
                    calibration.metadata.get('plane_normal'), self.buffer.samples)
            self.adoptions[source] = self.adoptions.get(source, 0) + 1
            self.misfit.reset()
            self.scheduler.calibration_changed()
            if reference.source != 'fit' or moved:
                reference.set(calibration, None, 'calibration')
        self.calibration = calibration  # last: whoever sees it in force sees it counted
        self._restart_tracker()

    def _recompensate(self, calibration: Calibration) -> None:
        """What the buffer and evidence hold was compensated by the compensation in force:
        move each reading by the difference ``calibration``'s makes at its own-field state
        (they were emptied before, and a robot that had just turned to calibrate had to turn
        again before ``~/calibrate`` could fit). The buffer's own fit described the old
        readings: the caller screens by the new calibration until the next reference fit, and
        a fit made of the old ones is abandoned (``_complete``)."""
        learner = self.compensation
        old = None if self.calibration is None else self.calibration.compensation

        def change(states: np.ndarray) -> np.ndarray:
            return learner.field_of(old, states) - learner.field_of(calibration.compensation,
                                                                    states)
        self.buffer.shift(change)
        self.evidence.shift(change)
        self.buffer_reference.provisional = None
        self.scheduler.reference_done(False)
        self._compensation_epoch += 1  # what waits to be learned is dropped (``_ingest``)

    def _sync_states(self) -> None:
        """The learner's inputs changed (parameters, a recording's columns): the states held
        were made of the old ones and are unknown from now on (``forget_states``)."""
        if self.compensation.specs is not self._state_specs:
            self._state_specs = self.compensation.specs
            self._state_epoch += 1
            for part in (self.buffer, self.evidence):
                part.forget_states(self.compensation.state_size)

    def _leave_plane(self) -> None:
        """The sensor left the plane its planar calibration was turned in: stop screening the
        buffer by it (it knows nothing off the plane) and refine from the first interval, so a
        full calibration is collected and judged at once. The planar one stays in force."""
        self.buffer_reference.set(None, None, None)
        self.scheduler.calibration_changed()
        self._event('info', 'the sensor moved out of the plane it was calibrated turning in: '
                            'collecting in 3-D for a full calibration (keep turning it through '
                            'every orientation); the planar calibration stays in force until a '
                            'better one is found')

    def _check_reference(self) -> None:
        """Set the buffer's reference aside once it refuses most of a window of readings."""
        stale = self.buffer_reference.stale()
        if stale is None:
            return
        source, refused, window = stale
        if source == 'fit':
            self.scheduler.reference_done(False)
        what = 'its own fit' if source == 'fit' else 'the calibration in force'
        self._event('info', f'the buffer stopped screening by {what}: it refused {refused} of '
                            f'the last {window} readings, so it no longer describes the sensor; '
                            'collecting without it')

    def _collect_anew(self, now: float) -> None:
        """After a misfit: forget samples and evidence from before it, keep the calibration."""
        self.buffer.clear()
        self.compensation.restart_mean()
        self._measured_coverage = None
        self.evidence.forget_before(now - MISFIT_WINDOW_S)
        self.scheduler.reset()
        self.buffer_reference.provisional = None
        self.buffer_reference.set(None, None, None)
        self.attitudes.clear()

    # -- online tracking -----------------------------------------------------------------------

    def _restart_tracker(self) -> None:
        self._last_taught = None
        self._last_tracking_check = None
        if self.settings.online_tracking and self.calibration is not None:
            self.tracker = OnlineTracker(self.calibration)
        else:
            self.tracker = None

    # -- state, reset --------------------------------------------------------------------------

    @property
    def state(self) -> str:
        if self.calibration is None:
            return 'collecting' if self.buffer.fill > 0 else 'uncalibrated'
        if self.misfit.misfit:
            return 'calibrated-misfit'
        if not self.settings.refine:
            return 'calibrated'
        return 'calibrated-converged' if self.scheduler.converged else 'calibrated-refining'

    @property
    def last_residual_pct(self) -> float | None:
        if self.calibration is None:
            return None
        return self.calibration.metadata_number('residual_rms_pct')

    def reset(self) -> None:
        """Empty the buffer and evidence, forget the stream's frame and stamps (a new sensor may
        follow); the calibration in force stays. A fit running now is abandoned."""
        self.buffer.clear()
        self._measured_coverage = None
        self.evidence.clear()
        self.screen.reset()
        self.scheduler.reset()
        self.misfit.reset()
        self.backlog.drop_held(self.accepted)
        self._epoch += 1
        self.buffer_reference.provisional = None
        self.buffer_reference.set(self.calibration, None,
                                  'calibration' if self.calibration else None)
        self._restart_tracker()
        self.attitudes.clear()
        self.pairing.clear()
        self.end_compensation_window('~/reset emptied what it was learning from')
        self.compensation.reset()
        for part in (self.hints, self.input_watch, self.alignment_wait):
            part.clear()
    def feed(self, samples: np.ndarray, rate_hz: float = 100.0, start_ns: int = 0,
             frame_id: str = '', accel: np.ndarray | None = None,
             gyro: np.ndarray | None = None) -> None:
        """Stream recorded rows through ``process`` stamped at ``rate_hz`` (offline use); ``accel``
        (and ``gyro``, rad/s) rows go through ``process_imu`` first with the same stamps."""
        step = 1e9 / rate_hz
        accel_rows = None if accel is None else np.asarray(accel, dtype=float).tolist()
        gyro_rows = None if gyro is None else np.asarray(gyro, dtype=float).tolist()
        for index, row in enumerate(np.asarray(samples, dtype=float).tolist()):
            stamp = start_ns + round(index * step)
            if accel_rows is not None:
                self.process_imu(stamp, frame_id, accel_rows[index],
                                 None if gyro_rows is None else gyro_rows[index])
            self.process(stamp, frame_id, row)

    # -- reporting -----------------------------------------------------------------------------

    def take_events(self) -> list[SessionEvent]:
        """What the session decided since the last call, oldest first."""
        events = list(self._events)
        self._events.clear()
        return events

    def _event(self, level: str, message: str, **kwargs) -> None:
        self._events.append(SessionEvent(level, message, **kwargs))

    @property
    def has_events(self) -> bool:
        return bool(self._events)

    def rejects(self) -> dict[str, int]:
        """Every refusal by reason: screening, then duplicates and magnitude outliers."""
        return {**self.screen.counts, **self.refusals}

    def coverage(self) -> Coverage:
        """The buffer's coverage now: of the heading circle if ``yaw_only``, else of the sphere."""
        if self.yaw_only():
            return self.heading_coverage().coverage
        return self.hints.dress(self.buffer.coverage())

    @property
    def held(self) -> int:
        """Readings received while a fit ran, not yet fed to the buffer (in order, later)."""
        return len(self.backlog)

    @property
    def hold_overflows(self) -> int:
        """Held readings fed at once because the backlog was full (``backlog.HOLD_LIMIT``)."""
        return self.backlog.overflows

    def reported_coverage(self) -> Coverage:
        """``coverage()`` for reports (diagnostics, the progress log), without its milliseconds
        on the caller's thread: what the fit worker measured with its latest check or readiness
        test (jobs.buffer_coverage), while no older than REPORTED_COVERAGE_AGE_S of stream and of
        the kind the buffer is now (a robot that starts turning); measured here otherwise.
        Heading coverage is looked at here, so its hint knows which way the robot turns."""
        measured = self._measured_coverage
        if (measured is None or self.clock.now - measured[0] > REPORTED_COVERAGE_AGE_S
                or (measured[1].cells == HEADING_SECTORS) != self.yaw_only()):
            return self.coverage()
        if measured[1].cells == HEADING_SECTORS:
            return self.heading_coverage().coverage
        return self.hints.dress(measured[1])

    def yaw_only(self) -> bool:
        """Whether coverage and hints are about the heading circle: model ``planar``, or
        ``auto`` with the buffer's samples round a ring when last judged (``hints.py``)."""
        return self.settings.model == 'planar' or (
            self.settings.model == 'auto' and self.hints.yaw_only)

    def heading_coverage(self) -> HeadingCoverage:
        """The buffer's heading coverage and the turn still needed, which way (milliseconds)."""
        return self.hints.heading(self.buffer.samples, self.buffer.readings)

    @property
    def frame_id(self) -> str:
        """The stream's frame, '' while unknown."""
        return self.screen.frame_id or ''

    @property
    def messages_received(self) -> int:
        """Messages given to ``process`` so far, refused ones included."""
        return self.input_rate.count

    @property
    def input_rate_hz(self) -> float:
        """Input messages per second, as the latest ``diagnostic_values`` measured them."""
        return self.input_rate.rate

    def view(self) -> CalibrationView:
        """The buffer's samples as the calibration in force sees them, for RViz."""
        return calibration_view(self.buffer.samples, self.buffer.counts, self.calibration)

    def progress_text(self, coverage: Coverage | None = None) -> str:
        """What to do next, e.g. 'coverage 63 % - keep rotating about the pitch axis (y)'."""
        if self.calibration is None and (self.input_watch.problem or self.alignment_wait.waiting):
            return self.input_watch.problem or self.alignment_wait.progress()
        return report.progress_text(self.state, self.calibration, coverage or self.coverage(),
                                    self.buffer, self.settings)

    def misfit_text(self) -> str:
        """Why the calibration in force does not fit, and what happens about it."""
        return report.misfit_text(self.misfit.last, self.units, self.settings.auto_calibrate)

    def new_screen_rejects(self) -> dict[str, int]:
        """Messages refused by screening since the previous call, by the reasons that occurred."""
        counts = self.screen.counts
        new = {reason: count - self._reported_rejects[reason]
               for reason, count in counts.items() if count > self._reported_rejects[reason]}
        self._reported_rejects = dict(counts)
        return new

    def diagnostic_values(self, now: float, coverage: Coverage | None = None
                          ) -> dict[str, object]:
        """Key/values for /diagnostics (report.diagnostic_values); read once per diagnostics
        period (updates the input rate)."""
        return {**report.diagnostic_values(self, now, coverage or self.coverage()),
                **self.input_watch.values(), **self.alignment_wait.values()}

    def diagnostics_level(self, coverage: Coverage, input_rate_hz: float,
                          problem: str | None = None, no_input: str = ''
                          ) -> tuple[report.Level, str]:
        """/diagnostics' level and message (report.diagnostics_level), the node's ``problem`` and
        the fit worker's first; refused messages are taken only when no problem outranks them."""
        problem = '; '.join(text for text in (problem, self.runner.problem) if text) or None
        return report.diagnostics_level(
            self.state, self.progress_text(coverage), input_rate_hz, no_input, problem=problem,
            refused=self.new_screen_rejects() if problem is None else None,
            misfit=self.misfit_text(), earth_warning=self.earth_warning(),
            alignment_warning=self.alignment_warning(), imu_warning=self.pairing.warning(),
            input_problem=self.input_watch.problem or self.input_watch.imu_problem)


__all__ = ['REFUSAL_REASONS', 'SCREEN_REASONS', 'STATES', 'CalibrationAttempt',
           'CalibrationSession', 'Processed', 'SessionEvent']
