# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
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
import math
import random

import numpy as np

from mag_calibrator_ros.calibration.fit.alignment import StaticAttitudes
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import Coverage
from mag_calibrator_ros.calibration.fit.earth_field import EarthField
from mag_calibrator_ros.calibration.fit.heading import PlaneWatch
from mag_calibrator_ros.calibration.fit.input_sanity import (
    calibration_unit_problem,
    compensation_bound_problems,
    field_limit,
)
from mag_calibrator_ros.calibration.live import report, verdicts
from mag_calibrator_ros.calibration.live.alignment_wait import AlignmentWait
from mag_calibrator_ros.calibration.live.backlog import DRAIN_PER_MESSAGE, Backlog, Reading
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.compensation import CompensationLearner
from mag_calibrator_ros.calibration.live.error_model import ErrorModel
from mag_calibrator_ros.calibration.live.events import (
    MAX_EVENTS,
    REFUSAL_REASONS,
    REFUSED,
    STATES,
    Processed,
    SessionEvent,
)
from mag_calibrator_ros.calibration.live.evidence import (
    HOLD_OUT_EVERY,
    MISFIT_WINDOW_S,
    HeldOutEvidence,
    MisfitMonitor,
)
from mag_calibrator_ros.calibration.live.findings import Findings
from mag_calibrator_ros.calibration.live.hints import MotionHints
from mag_calibrator_ros.calibration.live.jobs import REFERENCE_OPTIONS, FitJob, JobOutcome
from mag_calibrator_ros.calibration.live.pairing import Delivery, ImuPairing, RateMeter
from mag_calibrator_ros.calibration.live.reference import BufferReference
from mag_calibrator_ros.calibration.live.report import CalibrationAttempt
from mag_calibrator_ros.calibration.live.rotation_track import RotationTrack
from mag_calibrator_ros.calibration.live.sanity import InputWatch
from mag_calibrator_ros.calibration.live.scheduler import FitScheduler, Situation, StreamClock
from mag_calibrator_ros.calibration.live.screening import SCREEN_REASONS, ReadingScreen
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.live.tracker import Tracking
from mag_calibrator_ros.calibration.live.view import CalibrationView, calibration_view
from mag_calibrator_ros.calibration.live.worker import FitRunner, InlineRunner

PERIODIC_S = 1.0  # stream seconds between updates of the field's centre (evidence's cells)

class CalibrationSession:
    """The calibrator's state between messages: buffer, evidence, calibration in force, fits."""

    def __init__(
        self,
        settings: SessionSettings | None = None,
        calibration: Calibration | None = None,
        runner: FitRunner | None = None,
        metadata: Mapping[str, object] | None = None,
        *,
        pairing: ImuPairing | None = None,
        attitudes: StaticAttitudes | None = None,
        input_names: Sequence[str] | None = None,
    ) -> None:
        """``runner``: where fits run (inline by default; the node's is a process).
        ``metadata``: stamped on every fitted calibration ('units' the input's, tesla by
        default). A recording read offline brings its own ``pairing`` (an accelerometer in g or
        counts has no plausible range), ``attitudes`` (a log without stamps has no clock) and
        ``input_names`` (the own field's inputs it logged, fed by ``process_input``)."""
        self._settings = settings or SessionSettings()
        self._settings.check()
        self._runner = runner or InlineRunner()
        self._metadata = {'units': 'T', **(metadata or {})}  # stamped on every fit
        self._units = str(self._metadata['units'])
        self._buffer = SampleBuffer(self._settings.buffer_size, self._settings.k)
        self._screen = ReadingScreen(self._settings.full_scale_limit, self._units == 'T')
        self._evidence = HeldOutEvidence()
        self._scheduler = FitScheduler(self._settings.buffer_size)
        self._misfit = MisfitMonitor()
        self._errors = ErrorModel()
        self._clock = StreamClock()
        self._refusals = dict.fromkeys(REFUSAL_REASONS[len(SCREEN_REASONS):], 0)
        self._accepted = self._accepted_at_poll = self._implausible = 0  # _at_poll: idle?
        self._input_rate = RateMeter()
        self._calibration: Calibration | None = None  # only ``_put_in_force`` changes it
        self._last_attempt: CalibrationAttempt | None = None
        self._adoptions: dict[str, int] = {}  # these counts: ``report.SessionCounts``
        self._jobs_run: dict[str, int] = {}
        self._stale_dropped = 0
        self._tracking = Tracking()  # the online tracker of the calibration in force
        self._buffer_reference = BufferReference(self._buffer)
        self._backlog = Backlog()  # the readings that arrive while a fit runs
        self._compensation_epoch = 0  # bumped by each compensation put in force
        self._state_specs: tuple | None = None  # the own-field inputs the states are made of
        self._state_epoch = 0  # bumped when they change: states made before mean nothing
        self._job: FitJob | None = None
        self._job_epoch = (0, 0)  # (_epoch, _compensation_epoch) when the job was made
        self._epoch = 0  # bumped by reset(): outcomes of older jobs are stale
        self._next_ticket = 1
        self._hold_out = random.Random(0)
        self._next_periodic = 0.0
        self._events: deque[SessionEvent] = deque(maxlen=MAX_EVENTS)
        self._hints = MotionHints()  # the kind of hint, judged at stream points (hints.py)
        self._input_watch = InputWatch(self._units == 'T', self._settings.full_scale_limit)
        self._alignment_wait = AlignmentWait()  # the first calibration waits to be aligned
        self._attitudes = attitudes or StaticAttitudes()  # still ones paired, for alignment
        self._pairing = pairing or ImuPairing()
        self._turns = RotationTrack()  # the gyroscope's turning, for the gyro-aided fit
        self._findings = Findings()  # the model's field here, the latest alignment and check
        self._compensation = CompensationLearner(*self._settings.compensation)  # K u + c (T - T0)
        if input_names is not None:
            self._compensation.name_inputs(tuple(input_names))
        if calibration is not None:
            self.apply_calibration(calibration, 'given')

    # -- configuration -------------------------------------------------------------------------

    def reconfigure(self, settings: SessionSettings) -> None:
        """Adopt new settings; a resized buffer keeps its most unique samples."""
        settings.check()
        old, self._settings = self._settings, settings
        if (settings.buffer_size, settings.k) != (old.buffer_size, old.k):
            self._buffer.resize(settings.buffer_size, settings.k)
            self._scheduler.capacity = settings.buffer_size
        self._hints.measured(None)  # measured with the old settings (model, buffer)
        self._screen.full_scale = self._input_watch.full_scale = settings.full_scale_limit
        if settings.online_tracking != old.online_tracking:
            self._tracking.restart(self._calibration, self._settings.online_tracking)
        self._compensation.configure(*settings.compensation)

    def close(self) -> None:
        """Stop the fit worker (the node calls this on shutdown)."""
        self._runner.close()

    # -- per message ---------------------------------------------------------------------------
    # The path of one reading, a call of ``process`` (ARCHITECTURE.md, "A reading's path"):
    # screen (screening.ReadingScreen), pair (pairing.ImuPairing), learn (``_ingest``: a
    # held-out share to evidence.HeldOutEvidence, the rest to buffer.SampleBuffer and the
    # tracker; while a fit runs, readings wait in ``_hold`` and are fed afterwards in order, so
    # the result does not depend on how long the fit took), correct (``Calibration.apply``),
    # publish (``Processed``), schedule (scheduler.FitScheduler; ``_submit`` makes the
    # jobs.FitJob, ``_complete`` asks verdicts.py, ``_put_in_force`` is the one door).

    def process(self, stamp_ns: int, frame_id: str, field: Sequence[float],
                delivery: Delivery | None = None) -> Processed:
        """Screen one message, learn from it, and correct it with the calibration in force;
        ``delivery``, live, says how late it was handled (for the pairing's warnings)."""
        self._input_rate.count += 1
        try:
            x0, x1, x2 = (float(value) for value in field)
        except (TypeError, ValueError):
            x0 = x1 = x2 = math.nan
        for problem in self._input_watch.offer(stamp_ns, (x0, x1, x2)):  # each said once
            self._event('warning', problem)
        reason = self._screen.screen(stamp_ns, frame_id, x0, x1, x2)
        if self._screen.changes:
            for change in self._screen.take_changes():
                self._event('warning' if change.kind == 'frame' else 'info', change.message)
        if reason is not None:
            return REFUSED
        self._accepted += 1
        self._sync_states()
        reading, state = self._compensation.observe(stamp_ns, np.array((x0, x1, x2)),
                                                   self._calibration)
        if self._settings.gyro_aided:
            self._turns.add_reading(stamp_ns, reading)
        epochs = (self._compensation_epoch, self._state_epoch)
        decided = self._pairing.settle(stamp_ns, frame_id,
                                       Reading(reading, stamp_ns, epochs, state), delivery)
        self._imu_warnings()
        self._advance()
        for item, pair in decided:  # arrival order, each once its IMU sample could be there
            (self._hold if self._job is not None or len(self._backlog) else self._ingest)(
                item._replace(pair=pair))
        calibration = self._calibration
        if calibration is None:
            return Processed(True, None, None)
        corrected = calibration.apply(reading)
        size = float(np.linalg.norm(corrected))
        if not size <= self._field_limit():  # an input or term no robot has: never published
            self._implausible += 1
            self._event('warning', None if self._implausible > 1 else (
                f'a corrected field of {size:.3g} is beyond any the magnetometer reads: not '
                'published (an interference input or a compensation term is wrong)'))
            return Processed(True, None, None)
        sigma = self._errors.sigma(size)
        return Processed(True, corrected, calibration, math.hypot(sigma, self._misfit.uncertainty),
                         self._errors.along(corrected))

    def process_imu(self, stamp_ns: int, frame_id: str, accel: Sequence[float],
                    gyro: Sequence[float] | None = None,
                    delivery: Delivery | None = None) -> bool:
        """Keep one accelerometer (m/s^2) and gyroscope (rad/s) sample to pair magnetometer
        readings with (``ImuPairing.add``); False when refused, counted by reason: no plausible
        specific force, or ``frame_id`` not the magnetometer stream's (said once a frame)."""
        self._input_watch.offer_imu(stamp_ns, accel)
        kept = self._pairing.add(stamp_ns, accel, gyro, frame_id, self._screen.frame_id,
                                 delivery)
        if kept and gyro is not None and self._settings.gyro_aided:
            self._turns.add_rate(stamp_ns, gyro)
        if kept and gyro is not None and self._compensation.learning:
            self._compensation.gyro(stamp_ns, gyro)
        self._imu_warnings()
        return kept

    def process_temperature(self, stamp_ns: int | None, celsius: float) -> None:
        """One sensor temperature (degC, ``imu/temperature``) for the own field's drift."""
        self._event('warning', self._compensation.temperature(stamp_ns, celsius))

    def process_input(self, index: int, stamp_ns: int | None, value: float) -> None:
        """One sample of own-field input ``index`` (``interference_inputs``' order, or the
        ``input_names`` a recording gave), paired with readings by stamp."""
        self._event('warning', self._compensation.input(
            index, stamp_ns, value, self._calibration, self._field_limit()))

    def _field_limit(self) -> float | None:  # the largest term or corrected field there is
        calibration, full_scale = self._calibration, self._settings.full_scale_limit
        return None if calibration is None else field_limit(full_scale, calibration.field_strength)

    def finish(self) -> None:
        """The recording ends (offline): its last still stretch counts as an attitude too."""
        self._attitudes.finish()

    def _imu_warnings(self) -> None:
        for warning in self._pairing.take_warnings() if self._pairing.has_warnings else ():
            self._event('warning', warning)

    def set_earth_field(self, field: EarthField | None) -> None:
        """The World Magnetic Model's field here (None: unknown); used by the next fits."""
        self._findings.earth = field
        self._errors.expect_dip(None if field is None else field.inclination_deg)

    def poll(self) -> None:
        """Take a finished fit's outcome and feed held readings (``Backlog.budget``); the node
        calls this on a timer (messages call it too): answers arrive when no message does."""
        flowing = self._accepted != self._accepted_at_poll
        self._accepted_at_poll = self._accepted
        self._advance(budget=self._backlog.budget(flowing))

    def _advance(self, budget: int = DRAIN_PER_MESSAGE) -> None:
        if self._job is not None:
            outcome = self._runner.poll()
            if outcome is None:
                return
            self._job = None
            self._complete(outcome)
        while len(self._backlog) and self._job is None and budget > 0:
            self._ingest(self._backlog.next())
            budget -= 1
        if self._job is None and not len(self._backlog) and self._backlog.waiting:
            self._submit('request')

    def _hold(self, item: Reading) -> None:
        overflow = self._backlog.hold(item)
        if overflow is not None:  # the backlog is full: its oldest is fed now
            self._ingest(overflow)

    def _ingest(self, item: Reading) -> None:
        """Everything a reading teaches, in stream order (the held ones after the fit).

        ``epochs``: the compensation it was compensated by on arrival, and the inputs its
        own-field ``state`` is made of. One compensated by a compensation since replaced
        teaches nothing (their number depends on how long the fit took; on a loaded computer
        they failed the next fit, issue #22); a state of other inputs than today's is unknown."""
        reading, stamp_ns, epochs, state, pair = item
        now = self._clock.advance(stamp_ns)
        self._backlog.ingested += 1
        if epochs[0] != self._compensation_epoch:
            self._stale_dropped += 1
            return
        if epochs[1] != self._state_epoch:
            state = None
        if pair is not None and self._settings.align:
            self._attitudes.add(now, reading, pair[0], pair[1])
        if pair is not None and pair[2] is not None and self._calibration is not None:
            self._errors.observe_dip(self._calibration.apply(reading), pair[2])
        # Evidence judges a calibration: none yet, none needed. The draw is pseudo-random (and
        # deterministic), so a recording replayed again holds out other readings.
        if self._calibration is not None and self._hold_out.random() * HOLD_OUT_EVERY < 1.0:
            self._evidence.add(reading, self._buffer_reference.direction(reading), now, state)
        elif not self._misfit.world:  # a disturbance of the world teaches nothing
            if self._buffer_reference.left_plane(reading):
                self._leave_plane()
            outcome = self._buffer.add(reading, None if pair is None else pair[2], state)
            if outcome in self._refusals:
                self._refusals[outcome] += 1
            else:
                self._scheduler.sample_added(self._buffer.fill == self._buffer.capacity)
            if self._buffer_reference.source is not None:
                self._check_reference()
            self._tracking.teach(self._calibration, reading)
        if now >= self._next_periodic:
            self._next_periodic = now + PERIODIC_S
            self._update_centre()
            self._answer(self._compensation.window_answer(now, self._calibration))
        self._hints.learnt(now, self._buffer, reading)  # the kind of hint (hints.py)
        if self._job is None:
            situation = Situation.of(now, self._settings, self._buffer,
                                     self._calibration is not None, self._misfit,
                                     self._backlog.request_ready)
            kind = (self._scheduler.due(situation)
                    or (not self._misfit.world and self._compensation.due(now, self._calibration))
                    or self._gyro_due(now))
            if kind is not None:
                self._submit(kind)

    def _gyro_due(self, now: float) -> str | None:
        if not (self._settings.gyro_aided and self._settings.auto_calibrate):
            return None
        return self._turns.fit_due(now, self._calibration is not None,  # 'gyro', 'step'
                                   verdicts.gyro_improvable(self._calibration, self._misfit.world))

    def _update_centre(self) -> None:
        radius = 0.0
        if self._calibration is not None:
            radius = self._calibration.field_radius()
        elif self._buffer.fill >= 10:
            radius = self._buffer.field_radius()
        self._attitudes.field_scale = radius if radius > 0.0 else None
        self._buffer_reference.update_centre()

    # -- fits ----------------------------------------------------------------------------------

    def _submit(self, kind: str) -> None:
        ticket = self._backlog.take_request() if kind == 'request' else None
        if self._input_watch.refusal(kind):  # wrong units or normalised: nothing to put in force
            return self._refuse_fit(kind, ticket, self._input_watch.problem)
        job = self._make_job(kind, ticket)
        self._jobs_run[job.kind] = self._jobs_run.get(job.kind, 0) + 1
        self._job, self._job_epoch = job, (self._epoch, self._compensation_epoch)
        self._runner.submit(job)
        outcome = self._runner.poll()  # an inline runner has it already
        if outcome is not None:
            self._job = None
            self._complete(outcome)

    def _refuse_fit(self, kind: str, ticket: int | None, problem: str) -> None:
        now, period = self._clock.now, self._settings.auto_calibrate_period
        if kind == 'calibrate':  # tried again a period later: the input may be fixed by then
            self._scheduler.calibrate_done(now, True, period)
        if ticket is not None:
            attempt = CalibrationAttempt(False, f'calibration refused: {problem}')
            self._event('warning', attempt.message, ticket=ticket, attempt=attempt)

    def _make_job(self, kind: str, ticket: int | None) -> FitJob:
        buffer = self._buffer
        samples, weights, readings = buffer.samples, buffer.counts, buffer.readings
        metadata = {**self._metadata, 'frame_id': self._screen.frame_id or ''}
        alignment = self._settings.alignment_options(self._findings.earth)
        if kind == 'compensate':  # the robot's own field: live/compensation.py
            return self._compensation.job(self._calibration)
        if kind in ('gyro', 'step'):
            return FitJob(kind, np.zeros((0, 3)), None, None, self._settings.fit_options(),
                          metadata=metadata, current=self._calibration, alignment=alignment,
                          turned=self._turns.fit_snapshot(kind))
        if kind == 'reference':
            return FitJob('reference', samples, weights, readings, REFERENCE_OPTIONS,
                          previous=self._buffer_reference.provisional)
        if kind == 'check':
            recent = self._evidence.readings(since_s=self._clock.now - MISFIT_WINDOW_S)
            plane = self._buffer_reference.calibration_plane
            if plane is not None:  # a planar one knows nothing off its plane
                recent = recent[plane.near(recent)]
            return FitJob('check', samples, weights, readings, self._settings.fit_options(),
                          current=self._calibration, evidence=self._evidence.readings(),
                          recent=recent, tracked=self._tracking.calibration,
                          reference=buffer.reference)
        evidence = self._evidence.readings() if self._calibration is not None else None
        attitudes = self._attitudes.snapshot() if self._settings.align else None
        if attitudes is not None and not (len(attitudes) or self._pairing.paired):
            attitudes = None  # no IMU: the fit is not aligned
        return FitJob(
            'refine' if kind == 'refine' else 'calibrate', samples, weights, readings,
            self._findings.fit_options(self._settings, self._units), metadata=metadata,
            current=self._calibration, evidence=evidence, ticket=ticket,
            ready_coverage=self._settings.min_coverage if kind == 'calibrate' else None,
            reference=buffer.reference, attitudes=attitudes, alignment=alignment,
            earth=self._findings.earth_reference(self._settings, self._units),
            ups=buffer.ups if buffer.paired else None,
            paired=buffer.paired_readings if buffer.paired else None,
            turned=self._turns.snapshot() if kind == 'refine' and self._settings.gyro_aided
            else None,
        )

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
        if stale is not None and job.ticket is not None:
            attempt = CalibrationAttempt(False, f'calibration abandoned: {stale}', outcome)
            self._event('warning', attempt.message, ticket=job.ticket, attempt=attempt)
        if stale is not None:
            return
        if outcome.coverage is not None:
            self._hints.measured(self._clock.now, outcome.coverage)
        current = self._calibration
        if job.kind == 'reference':
            self._reference_done(outcome)
        elif job.kind == 'check':
            self._check_done(outcome)
        elif job.kind == 'compensate':
            verdict = self._compensation.judged(outcome, current)
            self._apply(verdict)
            self._answer(self._compensation.window_answer(self._clock.now, self._calibration,
                                                         verdict))
        elif job.kind == 'gyro':
            self._apply(verdicts.gyro_verdict(outcome, current, self._units))
        elif job.kind == 'step':
            self._misfit.offset_looked(self._clock.now, *verdicts.offset_look(outcome, current))
            verdict = verdicts.step_verdict(outcome, current, self._units, self._misfit.world)
            self._apply(verdict)
            if verdict.collect_anew:  # the old readings describe another sensor
                self._collect_anew(math.inf)
                self._turns.forget()
        elif job.ticket is not None:
            self._note_reference(outcome)
            verdict = verdicts.request_verdict(outcome, current, self._units, self._findings.earth)
            self._apply(verdict, job.ticket)
        elif job.kind == 'calibrate':
            self._scheduler.calibrate_done(self._clock.now, outcome.fitted or bool(outcome.error),
                                          self._settings.auto_calibrate_period)
            if outcome.result is not None and not outcome.error:
                self._note_reference(outcome)
            self._apply(self._alignment_wait.judge(
                verdicts.automatic_verdict(outcome, current, self._misfit.misfit, self._units,
                                           self._findings.earth),
                outcome, self._clock.now, self._pairing.paired > 0, self._settings.align))
        else:
            verdict = verdicts.refinement_verdict(outcome, current)
            self._apply(verdict)
            if not outcome.error:
                self._note_reference(outcome)
            if verdict.adopt is None:
                self._apply(verdicts.realign_verdict(outcome, current))
            self._scheduler.refine_done(verdicts.judged_on_evidence(outcome.comparison),
                                       verdict.adopt is not None)

    def _apply(self, verdict: verdicts.Verdict, ticket: int | None = None) -> None:
        """Record a verdict's attempt, put its calibration in force and log it. The event
        carries the attempt when it answers a request or puts the fit in force."""
        if verdict.attempt is not None:
            self._last_attempt = verdict.attempt
        adopted = verdict.adopt is not None
        if adopted:
            self._put_in_force(verdict.adopt, verdict.source)
        if verdict.message:
            carried = verdict.attempt if ticket is not None or adopted else None
            self._event(verdict.level, verdict.message, adopted=adopted, ticket=ticket,
                        attempt=carried)

    def _reference_done(self, outcome: JobOutcome) -> None:
        fit = outcome.reference
        self._scheduler.reference_done(fit is not None and fit.settled)
        if fit is not None:
            self._buffer_reference.provisional = fit.calibration
            self._buffer_reference.set(fit.calibration, fit.tolerance, 'fit')

    def _check_done(self, outcome: JobOutcome) -> None:
        """The calibration in force judged on recent evidence: misfit, and online tracking."""
        now = self._clock.now
        misfit_change = since_last_check_s = None
        if not outcome.error and outcome.job.current is self._calibration:
            misfit_change = self._misfit.update(now, outcome.fit_check)
            if misfit_change == 'cleared' and self._misfit.world_since is not None:
                self._evidence.forget_between(self._misfit.world_since, now)  # its readings
                self._turns.forget()
            if outcome.comparison is not None:
                since_last_check_s = self._tracking.checked(now)
        verdict = verdicts.check_verdict(outcome, self._calibration, misfit_change,
                                         since_last_check_s, self._settings, self._units,
                                         self._misfit.world,
                                         self._compensation.silence_note(self._calibration))
        self._event(verdict.level, verdict.message or None)
        if verdict.collect_anew:
            self._collect_anew(now)
        if verdict.adopt is not None:
            self._put_in_force(verdict.adopt, verdict.source)

    def _note_reference(self, outcome: JobOutcome) -> None:
        """Only a fit that passed its own gates (the model's aside) tells about the place."""
        for warning in self._findings.note(outcome) if verdicts.passed_own_gates(outcome) else ():
            self._event('warning', warning)

    def request_calibration(self) -> int:
        """Ask for a fit of the buffer (``~/calibrate``) once every reading received so far is
        in it (some may wait while another fit runs); the answer comes as an event with this
        ticket. A fit that passes the gates goes in force."""
        ticket = self._next_ticket
        self._next_ticket += 1
        self._backlog.request(ticket, self._accepted)  # after every reading received so far
        for item, pair in self._pairing.flush():  # those waiting for an IMU sample decided now
            self._hold(item._replace(pair=pair))
        self._advance()
        return ticket

    def request_compensation(self, timeout_s: float) -> int:
        """Learn the robot's own field now (``~/learn_compensation``): fits every few seconds
        of stream while its motors run through several currents, until one goes in force or
        ``timeout_s`` of stream pass (``CompensationLearner.open_window``); the answer comes
        as an event with this ticket."""
        ticket = self._next_ticket
        self._next_ticket += 1
        problem = self._compensation.open_window(ticket, self._clock.now, timeout_s,
                                                self._calibration, self._units)
        if problem:
            self._answer((ticket, CalibrationAttempt(False, problem)))
        return ticket

    def end_compensation_window(self, reason: str) -> None:
        """Answer an open ``request_compensation`` now with ``reason`` (the node's own deadline:
        stream time stands still while no reading comes)."""
        self._answer(self._compensation.close_window(reason))

    def _answer(self, answer: tuple[int, CalibrationAttempt] | None) -> None:
        if answer is not None:  # a success was logged when its compensation went in force
            ticket, attempt = answer
            self._event('debug' if attempt.success else 'warning', attempt.message,
                        ticket=ticket, attempt=attempt)

    # -- the calibration in force and the buffer's reference -----------------------------------

    def apply_calibration(self, calibration: Calibration, source: str = 'file') -> str | None:
        """Put a calibration in force at once (a file, parameters), or say why it cannot be: an
        offset beyond ``full_scale`` (another unit), or an own-field term beyond any field read."""
        limit, problem = self._settings.full_scale_limit, None
        if limit is not None and not np.max(np.abs(calibration.offset)) <= limit:
            problem = calibration_unit_problem(calibration.offset, calibration.field_strength,
                                               limit)
        elif calibration.compensation is not None:
            problem = '; '.join(compensation_bound_problems(calibration.compensation, field_limit(
                limit, calibration.field_strength), 'field units')) or None
        if problem is None:
            self._put_in_force(calibration, source)
        return problem

    def _put_in_force(self, calibration: Calibration, source: str) -> None:
        """The one door through which the calibration in force changes; ``source`` says why.

        A new calibration ('given', 'file', 'parameters', 'request', 'auto', 'refine', 'gyro',
        'step') is counted in ``adoptions`` and judged afresh: the misfit monitor, the scheduler
        and the tracker restart; it screens the buffer unless the buffer has a fit of its own.
        'realign' rotates the one in force into the IMU frame (only the tracker restarts);
        'tracking' steps it towards the tracker's (``tracked_updates``; the buffer's reference
        follows when it is the calibration in force; a static fit keeps the compensation)."""
        calibration = self._compensation.carry(calibration, self._calibration, source)
        self._sync_states()
        reference = self._buffer_reference
        if source == 'tracking':
            self._tracking.updates += 1
            if reference.source == 'calibration':
                reference.set(calibration, None, 'calibration')
            self._calibration = calibration
            return
        if source != 'realign':
            new = calibration.compensation
            in_force = None if self._calibration is None else self._calibration.compensation
            moved = not (new is in_force or (new is not None and new.same_field(in_force)))
            if moved:  # learned, or a file's
                self._recompensate(calibration)
            reference.calibration_plane = None
            if calibration.model == 'planar':
                reference.calibration_plane = PlaneWatch.of(
                    calibration.metadata.get('plane_normal'), self._buffer.samples)
            self._adoptions[source] = self._adoptions.get(source, 0) + 1
            self._misfit.reset()
            self._errors.restart(calibration)
            self._scheduler.calibration_changed()
            if reference.source != 'fit' or moved:
                reference.set(calibration, None, 'calibration')
        self._calibration = calibration  # last: whoever sees it in force sees it counted
        self._tracking.restart(self._calibration, self._settings.online_tracking)

    def _recompensate(self, calibration: Calibration) -> None:
        """What the buffer and evidence hold was compensated by the compensation in force:
        move each reading by the difference ``calibration``'s makes at its own-field state
        (they were emptied before, and a robot that had just turned to calibrate had to turn
        again before ``~/calibrate`` could fit). The buffer's own fit described the old
        readings: the caller screens by the new calibration until the next reference fit, and
        a fit made of the old ones is abandoned (``_complete``)."""
        old = None if self._calibration is None else self._calibration.compensation
        change = self._compensation.change(old, calibration.compensation)
        self._buffer.shift(change)
        self._evidence.shift(change)
        self._buffer_reference.provisional = None
        self._scheduler.reference_done(False)
        self._compensation_epoch += 1  # what waits to be learned is dropped (``_ingest``)

    def _sync_states(self) -> None:
        """The learner's inputs changed (parameters, a recording's columns): the states held
        were made of the old ones and are unknown from now on (``forget_states``)."""
        if self._compensation.specs is not self._state_specs:
            self._state_specs = self._compensation.specs
            self._state_epoch += 1
            for part in (self._buffer, self._evidence):
                part.forget_states(self._compensation.state_size)

    def _leave_plane(self) -> None:
        """The sensor left the plane its planar calibration was turned in: stop screening the
        buffer by it (it knows nothing off the plane) and refine from the first interval, so a
        full calibration is collected and judged at once. The planar one stays in force."""
        self._buffer_reference.set(None, None, None)
        self._scheduler.calibration_changed()
        self._event('info', report.LEFT_PLANE_TEXT)

    def _check_reference(self) -> None:
        """Set the buffer's reference aside once it refuses most of a window of readings."""
        stale = self._buffer_reference.stale()
        if stale is None:
            return
        source, refused, window = stale
        if source == 'fit':
            self._scheduler.reference_done(False)
        self._event('info', report.set_aside_text(source, refused, window))

    def _collect_anew(self, now: float) -> None:
        """After a misfit: forget the samples, and the evidence older than MISFIT_WINDOW_S
        before ``now`` (all of it at ``math.inf``); keep the calibration."""
        self._buffer.clear()
        self._compensation.restart_mean()
        self._hints.measured(None)
        self._evidence.forget_before(now - MISFIT_WINDOW_S)
        self._scheduler.reset()
        self._buffer_reference.provisional = None
        self._buffer_reference.set(None, None, None)
        self._attitudes.clear()

    # -- state, reset --------------------------------------------------------------------------

    def reset(self) -> None:
        """Empty the buffer and evidence, forget the stream's frame and stamps (a new sensor may
        follow); the calibration in force stays. A fit running now is abandoned."""
        self._collect_anew(math.inf)  # every sample and all evidence
        self._screen.reset()
        self._misfit.reset()
        self._backlog.drop_held(self._accepted)
        self._epoch += 1
        self._buffer_reference.set(self._calibration, None,
                                  'calibration' if self._calibration else None)
        self._tracking.restart(self._calibration, self._settings.online_tracking)
        self._pairing.clear()
        self._turns.reset()
        self.end_compensation_window('~/reset emptied what it was learning from')
        self._compensation.reset()
        for part in (self._hints, self._input_watch, self._alignment_wait):
            part.clear()
    # -- reporting -----------------------------------------------------------------------------

    def take_events(self) -> list[SessionEvent]:
        """What the session decided since the last call, oldest first."""
        events = list(self._events)
        self._events.clear()
        return events

    def _event(self, level: str, message: str | None, **kwargs) -> None:
        if message is not None:  # None: nothing to say (a problem said once already)
            self._events.append(SessionEvent(level, message, **kwargs))

    @property
    def calibration(self) -> Calibration | None:
        """The calibration in force (None: uncalibrated); only ``_put_in_force`` changes it."""
        return self._calibration

    def report(self, now: float | None = None, node: report.NodeStatus | None = None, *,
               measure_coverage: bool = False) -> report.SessionReport:
        """The session as people and tools see it (``report.SessionReport``). ``now`` (the
        caller's clock, seconds) marks a diagnostics period: the input rates are measured since
        the previous report that gave one, and the messages refused by screening since then
        can be the /diagnostics message; without it nothing is measured or consumed. ``node``:
        what the node adds (its problem, its values). Coverage costs no milliseconds here while
        the fit worker's latest measurement stands (``MotionHints.reported``); offline callers
        that want it measured now (milliseconds) ask with ``measure_coverage``."""
        hints, buffer, model = self._hints, self._buffer, self._settings.model
        coverage = (hints.coverage(buffer, model) if measure_coverage
                    else hints.reported(self._clock.now, buffer, model))
        state = self._state()
        counts = report.SessionCounts(
            received=self._input_rate.count, accepted=self._accepted,
            rejects={**self._screen.counts, **self._refusals}, adoptions=dict(self._adoptions),
            fits=dict(self._jobs_run), held=len(self._backlog),
            hold_overflows=self._backlog.overflows, held_out=len(self._evidence),
            stale_dropped=self._stale_dropped, tracked_updates=self._tracking.updates)
        watch, wait = self._input_watch, self._alignment_wait
        progress = report.progress_text(state, self._calibration, coverage, buffer, self._settings,
                                        watch.problem or (wait.progress() if wait.waiting else ''))
        parts = report.ReportInputs(
            settings=self._settings, units=self._units, state=state,
            calibration=self._calibration, buffer=self._buffer,
            screened_by=self._buffer_reference.source, evidence=self._evidence,
            misfit=self._misfit, errors=self._errors, input_rate=self._input_rate,
            pairing=self._pairing,
            attitudes=self._attitudes, counts=counts, last_attempt=self._last_attempt,
            tracker=self._tracking.tracker, findings=self._findings,
            earth_reference=self._findings.earth_reference(self._settings, self._units),
            compensation_values=self._compensation.diagnostic_values(
                self._calibration, self._units, self._clock.now),
            compensation_needs=self._compensation.needs(), runner=self._runner,
            input_values={**watch.values(), **self._alignment_wait.values()},
            input_problem=watch.problem or watch.imu_problem,
            waiting_for_alignment=self._alignment_wait.waiting,
            frame_id=self._screen.frame_id or '', progress=progress,
            earth_warning=self._findings.earth_warning(self._calibration, self._settings,
                                                       self._units))
        problem = (node is not None and node.problem) or self._runner.problem
        refused = self._screen.new_refusals() if now is not None and not problem else None
        return report.session_report(parts, now, coverage, node, refused)

    def view(self) -> CalibrationView:
        """The buffer's samples as the calibration in force sees them, for RViz."""
        buffer = self._buffer
        return calibration_view(buffer.samples, buffer.counts, self._calibration, buffer.anchors)

    def heading_coverage(self) -> Coverage:
        """Heading coverage and the turn still needed (ms: the turn in place asks 2/s)."""
        return self._hints.heading(self._buffer.samples, self._buffer.readings).coverage

    def _state(self) -> str:
        if self._calibration is None:
            return 'collecting' if self._buffer.fill > 0 else 'uncalibrated'
        if self._misfit.misfit:
            return 'calibrated-misfit'
        if not self._settings.refine:
            return 'calibrated'
        return 'calibrated-converged' if self._scheduler.converged else 'calibrated-refining'


__all__ = ['REFUSAL_REASONS', 'SCREEN_REASONS', 'STATES', 'CalibrationAttempt',
           'CalibrationSession', 'Processed', 'SessionEvent']
