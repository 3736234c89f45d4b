# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field: the model, its file, its fit, and the session learning it live.

``corrected = R M (raw - b - K u - c (T - T0))`` (fit/calibration.py ``Compensation``), learned
by fit/compensation.py, kept and adopted by live/compensation.py and verdicts.py.
"""

from __future__ import annotations

from dataclasses import replace
import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import (
    Calibration,
    CalibrationError,
    Compensation,
)
from mag_calibrator_ros.calibration.fit.compensation import (
    CompensationData,
    fit_compensation,
)
from mag_calibrator_ros.calibration.live.compensation import _Rows
from mag_calibrator_ros.calibration.live.evidence import compare_on_evidence
from mag_calibrator_ros.calibration.live.inputs import parse_input
from mag_calibrator_ros.calibration.live.jobs import run_job
from mag_calibrator_ros.calibration.live.offline import calibrate_now
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.live.worker import InlineRunner
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    load_calibration,
    save_calibration,
)
from mag_calibrator_ros.icm20948 import registers as reg

F = 50e-6
DIP = math.radians(60.0)
OFFSET = np.array([12e-6, -7e-6, 4e-6])
BATTERY = 'battery_state:sensor_msgs/msg/BatteryState:current'


def drive(seconds: float = 150.0, rate: float = 25.0, gain: float = 0.8e-6,
          drift: float = 0.2e-6, warm: float = 20.0, seed: int = 0,
          current: str = 'course') -> dict[str, np.ndarray]:
    """A ground robot on a course of turns in place, straight legs at several speeds and stops:
    its heading, a battery current drawn by its motion (amps), a die warming up (degC), and the
    magnetometer's raw field: Earth's field rotated by the heading, hard iron, ``gain`` tesla per
    amp along x and ``drift`` tesla per degC along x, with noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate)) / rate
    legs = [(8, 0.0, 0.6), (6, 0.5, 0.0), (3, 0.0, 0.0), (5, 1.0, 0.0), (4, 0.0, -0.8),
            (6, 0.3, 0.1), (3, 0.0, 0.0), (7, 0.8, -0.05), (5, 0.0, 0.5)]
    speed, yaw_rate = np.zeros(len(t)), np.zeros(len(t))
    start = 0.0
    while start < seconds:
        for duration, v, w in legs:
            chosen = (t >= start) & (t < start + duration)
            speed[chosen], yaw_rate[chosen] = v, w
            start += duration
    heading = np.cumsum(yaw_rate) / rate
    amps = 1.0 + 6.0 * np.abs(speed) + 4.0 * np.abs(yaw_rate)
    if current == 'constant':
        amps = np.full(len(t), 3.0)
    temperature = 25.0 + warm * (1.0 - np.exp(-t / 60.0))
    earth = np.stack([F * math.cos(DIP) * np.cos(heading), -F * math.cos(DIP) * np.sin(heading),
                      np.full(len(t), -F * math.sin(DIP))], axis=1)
    raw = (earth + OFFSET + np.outer(amps, [gain, 0.0, 0.0])
           + np.outer(temperature - 25.0, [drift, 0.0, 0.0])
           + rng.normal(0.0, 0.15e-6, (len(t), 3)))
    return {'t': t, 'raw': raw, 'current': amps, 'temperature': temperature,
            'heading': heading}


# -- the model ----------------------------------------------------------------------------------


def test_no_compensation_is_the_static_calibration_and_a_compensation_removes_its_field():
    static = Calibration(OFFSET, np.eye(3), F)
    zero = static.with_compensation(Compensation((BATTERY,), np.zeros((3, 1)), np.zeros(3)))
    raw = np.array([[30e-6, 1e-6, -40e-6], [5e-6, 20e-6, -39e-6]])
    assert np.allclose(zero.apply(raw, [[2.0], [3.0]], [30.0, 31.0]), static.apply(raw))
    compensated = static.with_compensation(
        Compensation((BATTERY,), [[1e-6], [0.0], [0.0]], [0.1e-6, 0.0, 0.0], 25.0))
    expected = static.apply(raw - np.array([[2e-6 + 0.5e-6, 0, 0], [3e-6 + 0.6e-6, 0, 0]]))
    assert np.allclose(compensated.apply(raw, [[2.0], [3.0]], [30.0, 31.0]), expected)
    assert np.allclose(compensated.apply(raw), static.apply(raw))  # no inputs: nothing removed
    scaled = compensated.scaled(1e6)  # microtesla
    assert np.allclose(scaled.apply(raw * 1e6, [[2.0], [3.0]], [30.0, 31.0]), expected * 1e6)


def test_an_invalid_compensation_is_refused_in_words():
    with pytest.raises(CalibrationError, match='3 x 1 numbers'):
        Compensation((BATTERY,), [1.0, 2.0])
    with pytest.raises(CalibrationError, match='needs reference_temperature'):
        Compensation((), None, [1e-7, 0.0, 0.0])
    with pytest.raises(CalibrationError, match='non-finite'):
        Compensation((BATTERY,), [math.nan, 0.0, 0.0])


# -- the file -----------------------------------------------------------------------------------


def test_the_file_keeps_k_c_and_t0_and_a_file_without_them_loads_unchanged(tmp_path):
    static = Calibration(OFFSET, np.eye(3), F, 'planar', {'time': '2026-01-01T00:00:00Z'})
    path = save_calibration(tmp_path / 'static.yaml', static)
    assert 'interference:' not in path.read_text()
    assert load_calibration(path).compensation is None
    learned = static.with_compensation(
        Compensation((BATTERY,), [[8e-7], [1e-8], [0.0]], [2e-7, 0.0, 0.0], 31.5),
        compensation_time='2026-01-02T00:00:00Z')
    path = save_calibration(tmp_path / 'learned.yaml', learned)
    loaded = load_calibration(path)
    assert loaded.compensation.inputs == (BATTERY,)
    assert np.allclose(loaded.compensation.interference, learned.compensation.interference)
    assert np.allclose(loaded.compensation.temperature_coefficient, [2e-7, 0.0, 0.0])
    assert loaded.compensation.reference_temperature == 31.5
    assert loaded.metadata['compensation_time'] == '2026-01-02T00:00:00Z'


def test_a_file_with_a_wrong_compensation_names_the_problem(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('mag_calibrator:\n  ros__parameters:\n    calibration:\n'
                    '      offset: [0.0, 0.0, 0.0]\n      matrix: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n'
                    '      field_strength: 5.0e-05\n'
                    '      interference_inputs: ["a:std_msgs/msg/Float64:data"]\n'
                    '      interference: [1.0e-06, 0.0]\n')
    with pytest.raises(CalibrationFileError, match='interference must have 3 numbers'):
        load_calibration(path)


# -- the fit ------------------------------------------------------------------------------------


def _data(run: dict[str, np.ndarray], names=('current',)) -> CompensationData:
    inputs = run['current'][:, None] if names else np.zeros((len(run['t']), 0))
    learn, held = slice(None, None, 2), slice(1, None, 2)
    return CompensationData(run['raw'][learn], inputs[learn], run['temperature'][learn],
                            tuple(names), run['raw'][held], inputs[held],
                            run['temperature'][held])


def _static(run: dict[str, np.ndarray]) -> Calibration:
    """A static calibration made while the current flowed: its offset holds the mean K u."""
    return Calibration(OFFSET + np.array([0.8e-6 * run['current'].mean(), 0.0, 0.0]),
                       np.eye(3), F)


def test_k_and_c_are_learned_within_ten_percent_of_the_truth():
    run = drive(seconds=120.0)
    fit = fit_compensation(_data(run), _static(run))
    compensation = fit.calibration.compensation
    assert fit.kept == ('current', 'temperature')
    assert compensation.interference[0, 0] == pytest.approx(0.8e-6, rel=0.1)
    assert np.all(np.abs(compensation.interference[1:, 0]) < 0.08e-6)
    assert compensation.temperature_coefficient[0] == pytest.approx(0.2e-6, rel=0.1)
    assert fit.held_candidate_pct < 0.5 * fit.held_current_pct


def test_nothing_is_learned_from_nothing():
    run = drive(seconds=120.0, gain=0.0, drift=0.0)
    fit = fit_compensation(_data(run), Calibration(OFFSET, np.eye(3), F))
    assert fit.calibration is None
    assert fit.kept == ()
    assert 'nothing to compensate' in fit.reason


def test_a_constant_current_says_what_motion_it_needs():
    run = drive(seconds=120.0, current='constant', drift=0.0, warm=0.5)
    fit = fit_compensation(_data(run), Calibration(OFFSET, np.eye(3), F))
    assert fit.calibration is None
    assert "input 'current' did not vary: drive at several speeds" in fit.reason
    assert 'the temperature varied' in fit.reason


# -- live ---------------------------------------------------------------------------------------


def _stream(session: CalibrationSession, run: dict[str, np.ndarray],
            corrupt: slice | None = None) -> list[np.ndarray]:
    out = []
    for index, when in enumerate(run['t']):
        stamp = int(round(when * 1e9)) + 1
        if index % 5 == 0:
            session.process_temperature(stamp, float(run['temperature'][index]))
        session.process_input(0, stamp, float(run['current'][index]))
        reading = run['raw'][index]
        if corrupt is not None and corrupt.start <= index < corrupt.stop:
            reading = reading + 1.0  # a tesla: refused by screening (beyond full scale)
        processed = session.process(stamp, 'imu', reading)
        out.append(processed.corrected if processed.corrected is not None
                   else np.full(3, np.nan))
    return out


def _heading_rms_deg(corrected: np.ndarray, heading: np.ndarray) -> float:
    error = np.degrees(np.arctan2(-corrected[:, 1], corrected[:, 0])) - np.degrees(heading)
    error = (error + 180.0) % 360.0 - 180.0
    error = error[np.isfinite(error)]
    error = (error - np.median(error) + 180.0) % 360.0 - 180.0
    return float(np.sqrt(np.mean(error ** 2)))


class _Recording(InlineRunner):
    """The inline runner, keeping what each compensation fit was given: the readings the
    session kept to learn from (and held out), with their stamps and inputs."""

    def __init__(self) -> None:
        super().__init__()
        self.learned_from: list[CompensationData] = []

    def submit(self, job) -> None:
        if job.kind == 'compensate':
            self.learned_from.append(job.compensation)
        super().submit(job)


def test_the_session_learns_the_current_and_temperature_live_and_adopts_them_on_evidence():
    run = drive(seconds=150.0)
    static = _static(run)
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=static)
    corrected = np.array(_stream(session, run))
    assert session.report().counts.adoptions.get('compensation', 0) >= 1
    compensation = session.calibration.compensation
    assert compensation.interference[0, 0] == pytest.approx(0.8e-6, rel=0.1)
    assert compensation.temperature_coefficient[0] == pytest.approx(0.2e-6, rel=0.1)
    last = run['t'] >= 120.0
    before = _heading_rms_deg(static.apply(run['raw'][last]), run['heading'][last])
    after = _heading_rms_deg(corrected[last], run['heading'][last])
    assert after < 0.25 * before
    values = session.report(0.0, measure_coverage=True).values
    assert values['interference_uT_per_unit[' + BATTERY + ']'][0] == pytest.approx(0.8, rel=0.1)
    assert 'compensation_time' in values
    session.reset()  # ~/reset forgets what was kept to learn from; the one in force stays
    assert session.report(0.0, measure_coverage=True).values['compensation_readings_kept'] == 0


def test_the_session_never_learns_from_nothing_or_from_refused_readings():
    run = drive(seconds=120.0, gain=0.0, drift=0.0)
    static = Calibration(OFFSET, np.eye(3), F)
    runner = _Recording()
    full_scale = reg.MEASUREMENT_LIMIT * reg.TESLA_PER_LSB  # the node's AK09916 limit
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,),
                                                 full_scale=full_scale),
                                 calibration=static, runner=runner)
    _stream(session, run, corrupt=slice(100, 400))
    assert session.calibration.compensation is None
    counts = session.report().counts
    assert 'compensation' not in counts.adoptions
    assert counts.rejects['out_of_range'] + counts.rejects.get('saturated', 0) >= 300
    # a fit is given every reading kept so far (a ring of 4000 rows, not filled in 120 s): the
    # last one, long after the corrupt stretch, every one kept before it
    last = runner.learned_from[-1]
    assert last.times[0] < 4.0 < 16.0 < last.times[-1]
    for data in runner.learned_from:  # no refused reading among them, kept or held out
        assert len(data.raw) and np.all(np.abs(data.raw) < 1e-3)
        assert np.all(np.abs(data.held_raw) < 1e-3)


def test_a_reading_before_the_first_temperature_sample_does_not_keep_the_temperature_out():
    """Issue #22: the temperature comes on its own topic, and a loaded computer can deliver
    the first one after the first magnetometer reading. That reading was kept without a
    temperature, and one such reading kept the temperature term out of every later fit (and
    biased K with the drift it left)."""
    run = drive(seconds=60.0, rate=20.0)
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=_static(run))
    for index, when in enumerate(run['t']):
        stamp = int(round(when * 1e9)) + 1
        session.process_input(0, stamp, float(run['current'][index]))
        if index % 4 == 1:  # the first temperature sample after the first reading
            session.process_temperature(stamp, float(run['temperature'][index]))
        session.process(stamp, 'imu', run['raw'][index])
    compensation = session.calibration.compensation
    assert compensation.temperature_coefficient[0] == pytest.approx(0.2e-6, rel=0.1)
    assert compensation.interference[0, 0] == pytest.approx(0.8e-6, rel=0.1)


class _SlowRunner:
    """A fit worker on a loaded computer: each outcome comes back ``delay`` polls (messages)
    after its job was submitted, so readings are held meanwhile."""

    problem = None
    restarts = 0
    last_restart = ''

    def __init__(self, delay: int) -> None:
        self.delay, self.job, self.left = delay, None, 0

    @property
    def busy(self) -> bool:
        return self.job is not None

    def submit(self, job) -> None:
        self.job, self.left = job, self.delay

    def poll(self):
        if self.job is None or self.left > 0:
            self.left -= self.job is not None
            return None
        job, self.job = self.job, None
        return run_job(job)

    def close(self) -> None:
        pass


def test_readings_held_while_a_compensation_was_learned_never_refill_the_buffer():
    """Issue #22: readings that arrive while a fit runs are held, compensated by the
    compensation in force on arrival (none, the first time). A learned one put in force emptied
    the buffer (it now moves it); the held ones then refilled it, and the more of them the
    slower the worker (a loaded computer), so the next ~/calibrate failed on a residual of
    5-6 %."""
    run = drive(seconds=100.0, rate=20.0)
    static = Calibration(OFFSET + np.array([0.8e-6 * 3.0, 0.0, 0.0]), np.eye(3), F)
    session = CalibrationSession(
        SessionSettings(interference_inputs=(BATTERY,), auto_calibrate=False, refine=False),
        calibration=static, runner=_SlowRunner(50))
    _stream(session, run)
    later = drive(seconds=100.0, rate=20.0)
    later['t'] = later['t'] + run['t'][-1] + 1.0
    _stream(session, later)
    counts = session.report().counts
    assert counts.adoptions.get('compensation', 0) >= 1
    assert counts.stale_dropped > 0
    attempt = calibrate_now(session, pause_s=0.0)  # _SlowRunner counts polls, not time
    assert attempt.success, attempt.message
    assert session.calibration.metadata_number('residual_rms_pct') < 2.0


def test_a_compensation_put_in_force_moves_what_the_buffer_holds_instead_of_emptying_it():
    """A robot that turned to calibrate, then had its own field's compensation put in force,
    had to turn again before ~/calibrate could fit: the buffer and evidence were emptied (the
    readings in them were compensated by the one before). Each is now moved by the difference
    the new compensation makes at its own inputs and temperature, merged points by their mean."""
    run = drive(seconds=100.0, rate=20.0)
    static = _static(run)
    settings = SessionSettings(interference_inputs=(BATTERY,), auto_calibrate=False,
                               refine=False, learn_compensation=False)
    session = CalibrationSession(settings, calibration=static)
    _stream(session, run)

    exact = Calibration(OFFSET, np.eye(3), F)

    def spread(samples: np.ndarray) -> float:
        return float(np.std(np.linalg.norm(exact.apply(samples), axis=1) / F))

    before, held = session.view().raw, session.report().counts.held_out
    true = Compensation(('current',), np.array([[0.8e-6], [0.0], [0.0]]),
                        np.array([0.2e-6, 0.0, 0.0]), 25.0)
    session.apply_calibration(exact.with_compensation(true), 'file')
    after = session.view().raw
    assert len(after) == len(before) and session.report().counts.held_out == held
    assert spread(after) < 0.2 * spread(before)  # on the static sphere once compensated
    attempt = calibrate_now(session)  # no turn since
    assert attempt.success, attempt.message
    assert session.calibration.metadata_number('residual_rms_pct') < 1.0
    session.apply_calibration(static, 'file')  # and back: the own field is in them again
    assert spread(session.view().raw) == pytest.approx(spread(before), rel=0.05)


def test_new_inputs_make_the_states_held_unknown_wherever_they_wait():
    """The inputs changed at run time (``interference_inputs``): states made of the old ones,
    in the buffer, the evidence or readings waiting while a fit runs, mean nothing. A
    compensation put in force before the next reading forgets the points made of them instead
    of reading their values as the new inputs' (or failing on their length); a waiting reading
    goes in with its state unknown."""
    run = drive(seconds=60.0, rate=20.0)
    one = SessionSettings(interference_inputs=(BATTERY,), auto_calibrate=False, refine=False,
                          learn_compensation=False)
    two = replace(one, interference_inputs=(
        BATTERY, 'motor_state:sensor_msgs/msg/BatteryState:current'))
    runner = _SlowRunner(50)
    session = CalibrationSession(one, calibration=_static(run), runner=runner)
    _stream(session, run)
    report = session.report()
    assert report.counts.held > 0 and report.buffer.fill > 0  # fits ran: readings wait
    session.reconfigure(two)
    both = Compensation(two.interference_inputs, np.array([[0.8e-6, 0.0], [0.0] * 2, [0.0] * 2]))
    session.apply_calibration(Calibration(OFFSET, np.eye(3), F).with_compensation(both), 'file')
    report = session.report()
    assert report.buffer.fill == 0 and report.counts.held_out == 0  # nothing could be moved
    later = drive(seconds=30.0, rate=20.0)
    later['t'] = later['t'] + run['t'][-1] + 1.0
    _stream(session, later)
    assert session.report().counts.held > 0
    session.reconfigure(one)  # what waits was made of two inputs
    while session.report().counts.held or runner.busy:
        session.poll()
    assert session.report().buffer.fill > 0  # in, their states unknown
    session.apply_calibration(_static(run).with_compensation(
        Compensation((BATTERY,), np.array([[0.8e-6], [0.0], [0.0]]))), 'file')
    assert session.report().buffer.fill == 0


def test_a_fit_made_before_a_compensation_went_in_force_is_abandoned():
    """A request's fit runs while a file's compensation is loaded: it fitted readings that
    have since moved, so its answer says so instead of putting them in force."""
    run = drive(seconds=60.0, rate=20.0)
    settings = SessionSettings(interference_inputs=(BATTERY,), auto_calibrate=False,
                               refine=False, learn_compensation=False)
    runner = _SlowRunner(5)
    session = CalibrationSession(settings, calibration=_static(run), runner=runner)
    _stream(session, run)
    while session.report().counts.held or runner.busy:
        session.poll()
    ticket = session.request_calibration()  # its fit runs now
    assert runner.job is not None and runner.job.ticket == ticket
    true = Compensation(('current',), np.array([[0.8e-6], [0.0], [0.0]]))
    session.apply_calibration(Calibration(OFFSET, np.eye(3), F).with_compensation(true), 'file')
    later = drive(seconds=2.0, rate=20.0)
    later['t'] = later['t'] + run['t'][-1] + 1.0
    _stream(session, later)
    [answer] = [event.attempt for event in session.take_events() if event.ticket == ticket]
    assert not answer.success and 'went in force while it ran' in answer.message
    assert session.calibration.compensation.same_field(true)


def test_a_bad_input_spec_is_refused_with_the_form_it_needs():
    problems = SessionSettings(interference_inputs=('battery current',)).problems()
    assert any('topic:package/msg/Type:field' in problem for problem in problems)
    spec = parse_input('cmd_vel:geometry_msgs/Twist:abs(linear.x)')
    assert spec.type == 'geometry_msgs/msg/Twist' and spec.absolute

    class Twist:
        class linear:  # noqa: N801 - the message's field
            x = -0.4
    assert spec.value(Twist()) == pytest.approx(0.4)


ODOMETRY = 'odom:nav_msgs/msg/Odometry:twist.twist.linear.x'


@pytest.mark.parametrize('inputs', [(), (BATTERY, ODOMETRY), (ODOMETRY,)])
def test_a_calibration_naming_inputs_this_node_lacks_is_applied_without_them(inputs):
    """A file learnt with other interference inputs (another count, or names this node does not
    subscribe): the reading is still corrected (those terms left out) and /diagnostics says so,
    where a shape error in the message path would stop the output."""
    run = drive(seconds=5.0)
    static = _static(run).with_compensation(
        Compensation(('current', 'wheel_speed', 'fan'), np.full((3, 3), 1e-7), np.zeros(3)))
    session = CalibrationSession(
        SessionSettings(interference_inputs=inputs, use_temperature=False), calibration=static)
    for index, when in enumerate(run['t'][:50]):
        stamp = int(round(when * 1e9)) + 1
        for j in range(len(inputs)):
            session.process_input(j, stamp, float(run['current'][index]))
        processed = session.process(stamp, 'imu', run['raw'][index])
        np.testing.assert_allclose(processed.corrected, static.apply(run['raw'][index]))
    assert 'interference_inputs does not list' in session.report(
        0.0, measure_coverage=True).values['interference_unmatched']


def test_inputs_whose_callbacks_run_after_the_readings_are_paired_by_stamp():
    """Under load a battery_state callback may run after the imu/mag messages stamped with it:
    the kept reading waits for its input's sample instead of taking an older one (which, at a
    current step, teaches a fraction of K)."""
    run = drive(seconds=150.0)
    runner = _Recording()
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=_static(run), runner=runner)
    late = 6  # each current sample handed over six readings (0.24 s) after its own reading
    stamps = [int(round(when * 1e9)) + 1 for when in run['t']]
    for index, stamp in enumerate(stamps):
        if index % 5 == 0:
            session.process_temperature(stamp, float(run['temperature'][index]))
        if index >= late:
            session.process_input(0, stamps[index - late], float(run['current'][index - late]))
        session.process(stamp, 'imu', run['raw'][index])
    assert runner.learned_from and runner.learned_from[-1].times[-1] > 140.0
    for data in runner.learned_from:  # every reading a fit learned from, kept or held out
        for times, inputs in ((data.times, data.inputs), (data.held_times, data.held_inputs)):
            truth = np.interp(times, run['t'] + 1e-9, run['current'])
            assert len(times) and np.abs(inputs[:, -1] - truth).max() < 1e-9  # its own sample
    assert session.calibration.compensation.interference[0, 0] == pytest.approx(0.8e-6, rel=0.1)


def test_held_out_readings_at_several_currents_span_their_headings_as_corrected():
    """A turn in place at one current, then a straight leg at several: the current's field moves
    the raw readings of the leg off the turn's ring, so their own shape spans nothing; as the
    calibrations correct them they span the turn's headings, and the learned compensation is
    judged on them (issue #26: after a quick procedure nothing more was judged for a minute)."""
    rng = np.random.default_rng(3)
    gain = np.array([1.6e-6, 0.0, 0.0])  # tesla per amp
    turn = np.linspace(0.0, 2.0 * math.pi, 50, endpoint=False)
    legs = np.full(90, 0.4)  # most held-out readings: one leg, the current stepping
    heading = np.concatenate([turn, legs])
    amps = np.concatenate([np.full(50, 1.0), np.tile(np.linspace(0.5, 5.0, 15), 6)])
    earth = np.stack([F * math.cos(DIP) * np.cos(heading), -F * math.cos(DIP) * np.sin(heading),
                      np.full(len(heading), -F * math.sin(DIP))], axis=1)
    raw = earth + OFFSET + np.outer(amps, gain) + rng.normal(0.0, 0.1e-6, (len(amps), 3))
    current = Calibration(OFFSET + gain, np.eye(3), F)  # the turn's static fit: right at 1 A
    candidate = Calibration(OFFSET, np.eye(3), F).with_compensation(
        Compensation(('current',), gain[:, None], np.zeros(3), None))
    comparison = compare_on_evidence(current, candidate, raw, amps[:, None], None)
    assert comparison.span >= 0.9, comparison.reason
    assert comparison.better, comparison.reason


def test_kept_rows_are_the_latest_in_arrival_order_past_their_limit():
    """Gyroscope pairs search the kept rows by time: the copy a fit gets is oldest first."""
    rows = _Rows(5, 2)
    for index in range(3):
        rows.append((float(index), -float(index)))
    assert rows.copy()[:, 0].tolist() == [0.0, 1.0, 2.0]
    for index in range(3, 12):
        rows.append((float(index), -float(index)))
    assert len(rows) == 5 and rows.copy()[:, 0].tolist() == [7.0, 8.0, 9.0, 10.0, 11.0]
    assert rows.copy()[:, 1].tolist() == [-7.0, -8.0, -9.0, -10.0, -11.0]
    rows.clear()
    assert len(rows) == 0 and rows.copy().shape == (0, 2)
