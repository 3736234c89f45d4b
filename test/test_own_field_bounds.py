# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field never makes a field no magnetometer reads (issue #47, items 2, 3, 6).

A glitched input sample (a battery driver's 65535 "unknown"), a temperature in kelvin or
Fahrenheit, a hand-edited file with K = 1e300 T/A: each is refused in words, and nothing the
session publishes as corrected is beyond what the magnetometer reads.
"""

from __future__ import annotations

from dataclasses import replace
import math
from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration, Compensation
from mag_calibrator_ros.calibration.fit.compensation import fit_compensation
from mag_calibrator_ros.calibration.live.inputs import parse_input
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    load_calibration,
)

F = 50e-6
OFFSET = np.array([12e-6, -7e-6, 4e-6])
BATTERY = 'battery_state:sensor_msgs/msg/BatteryState:current'
GAIN = 2e-6  # tesla per amp along x, the K
EARTH = np.array([F * 0.5, 0.0, -F * math.sqrt(0.75)])
FULL_SCALE = 4.9e-3
sys.path.insert(0, str(Path(__file__).parent))


def _session(full_scale: float = FULL_SCALE) -> CalibrationSession:
    """A session with K = 2 µT/A in force, one battery current subscribed."""
    calibration = Calibration(OFFSET, np.eye(3), F).with_compensation(
        Compensation((BATTERY,), [[GAIN], [0.0], [0.0]], np.zeros(3)))
    return CalibrationSession(
        SessionSettings(interference_inputs=(BATTERY,), use_temperature=False,
                        auto_calibrate=False, full_scale=full_scale), calibration=calibration)


def _corrected_after(session: CalibrationSession, currents: list[float]) -> list:
    """Each current sample, then a reading taken at 3 A (the true current throughout)."""
    corrected = []
    for index, current in enumerate(currents):
        stamp = (index + 1) * 20_000_000
        session.process_input(0, stamp, current)
        raw = EARTH + OFFSET + np.array([GAIN * 3.0, 0.0, 0.0])
        corrected.append(session.process(stamp + 1, 'imu', raw).corrected)
    return corrected


@pytest.mark.parametrize('glitch', [65535.0, 5000.0, math.inf, -32768.0])
def test_one_glitched_input_sample_is_dropped_and_said_once(glitch):
    """The issue's reproduction: one 65535 A BatteryState current published a 0.131 T field
    with K = 2 µT/A in force. The glitch is dropped, said once, and the field stays corrected
    with the last current that could be true."""
    session = _session()
    corrected = _corrected_after(session, [3.0, glitch, 3.0, glitch, 3.0])
    for field in corrected:
        np.testing.assert_allclose(field, EARTH, atol=1e-12)
    said = [event.message for event in session.take_events() if 'sample dropped' in event.message]
    assert len(said) == 1 and BATTERY in said[0]


def test_an_input_whose_own_field_the_chip_could_not_read_is_dropped():
    """900 A is a current some robot draws, but under K = 10 µT/A it puts 9 mT on a 4.9 mT
    magnetometer, which then could not read the field it reads: not this robot's current."""
    session = _session()
    calibration = session.calibration.with_compensation(
        Compensation((BATTERY,), [[10e-6], [0.0], [0.0]], np.zeros(3)))
    assert session.apply_calibration(calibration) is None
    session.process_input(0, 10, 3.0)
    session.process_input(0, 20, 900.0)
    raw = EARTH + OFFSET + np.array([10e-6 * 3.0, 0.0, 0.0])
    np.testing.assert_allclose(session.process(30, 'imu', raw).corrected, EARTH, atol=1e-12)
    said = ' '.join(event.message for event in session.take_events())
    assert 'beyond the 0.0049 it reads' in said


def test_the_kind_of_input_bounds_its_samples():
    current, speed = parse_input(BATTERY), parse_input(
        'cmd_vel:geometry_msgs/msg/Twist:abs(linear.x)')
    assert current.sample_problem(-40.0) is None and current.sample_problem(math.nan) is None
    assert 'current (1000 A)' in current.sample_problem(2000.0)
    assert '"unknown"' in current.sample_problem(65535.0)
    assert speed.sample_problem(3.0) is None and 'm/s' in speed.sample_problem(340.0)


def test_a_temperature_in_kelvin_or_a_fahrenheit_step_is_dropped_in_words():
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    session.process_temperature(1_000_000_000, 25.0)
    session.process_temperature(1_100_000_000, 77.0)  # another publisher, in °F
    session.process_temperature(60_000_000_000, 31.0)  # a minute later, warmer: a die's pace
    said = [event.message for event in session.take_events()]
    assert len(said) == 1 and 'no die warms so fast' in said[0]
    restarted = CalibrationSession(SessionSettings(auto_calibrate=False))
    for index, celsius in enumerate((45.0, 25.0, 25.1, 25.1, 25.2)):  # a level that stays
        restarted.process_temperature(1_000_000_000 + index * 100_000_000, celsius)
    assert restarted.report(0.0).values.get('temperature_degC') == pytest.approx(25.2)
    kelvin = CalibrationSession(SessionSettings(auto_calibrate=False))
    kelvin.process_temperature(1_000_000_000, 298.15)
    assert 'kelvin' in ' '.join(event.message for event in kelvin.take_events())


@pytest.mark.parametrize('line, words', [
    ('interference: [1.0e+300, 0.0, 0.0]', "interference for 'current' is 1e+300 T per unit"),
    ('temperature_coefficient: [1.0e+300, 0.0, 0.0]\n      reference_temperature: 25.0',
     'temperature_coefficient is 1e+300 T per degC'),
    ('temperature_coefficient: [1.0e-07, 0.0, 0.0]\n      reference_temperature: 1.0e+300',
     'reference_temperature 1e+300 degC is outside -60 to 200 degC'),
])
def test_a_hand_edited_file_with_absurd_terms_is_refused_naming_the_term_and_bound(
        tmp_path, line, words):
    """The issue's reproduction: ``~/load`` of K = 1e300 T/A or T0 = 1e300 degC was accepted
    and published fields of 2e300 T and 1e293 T."""
    path = tmp_path / 'edited.yaml'
    path.write_text('mag_calibrator:\n  ros__parameters:\n    calibration:\n'
                    '      offset: [0.0, 0.0, 0.0]\n      matrix: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n'
                    '      field_strength: 5.0e-05\n      interference_inputs: ["current"]\n'
                    f'      {line}\n')
    if 'interference:' not in line:
        path.write_text(path.read_text() + '      interference: [1.0e-06, 0.0, 0.0]\n')
    with pytest.raises(CalibrationFileError, match='beyond|outside') as raised:
        load_calibration(path)
    assert words in str(raised.value)


def test_a_corrected_field_beyond_any_the_chip_reads_is_never_published_as_corrected():
    """A calibration that scales the field a millionfold passes every shape check; what it
    makes of a reading is no field, and the session publishes it as none (said once)."""
    calibration = Calibration(OFFSET, np.eye(3) * 1e6, F)
    session = CalibrationSession(SessionSettings(auto_calibrate=False), calibration=calibration)
    for stamp in (10, 20, 30):
        processed = session.process(stamp, 'imu', EARTH + OFFSET)
        assert processed.accepted and processed.corrected is None
    said = [event.message for event in session.take_events() if 'not published' in event.message]
    assert len(said) == 1


def test_two_inputs_that_never_vary_apart_are_named_and_the_first_fitted_alone():
    """Issue #47: two topics of one battery's current listed as two inputs left K1 = -K2 as
    good a fit as the truth. The second is named as varying only with the first, and the first
    is learned as if alone."""
    from test_compensation import _data, _static, drive

    run = drive(seconds=120.0)
    data = _data(run)
    both = replace(data, inputs=np.column_stack([data.inputs[:, 0], 0.5 * data.inputs[:, 0]]),
                   held_inputs=np.column_stack([data.held_inputs[:, 0],
                                                0.5 * data.held_inputs[:, 0]]),
                   names=('current', 'current_again'))
    fit = fit_compensation(both, _static(run))
    again = next(report for report in fit.terms if report.name == 'current_again')
    assert "never varied apart from 'current'" in again.need and not again.determined
    assert fit.kept[0] == 'current' and 'current_again' not in fit.kept
    gains = fit.calibration.compensation.interference
    assert gains[0, 0] == pytest.approx(0.8e-6, rel=0.1) and not np.any(gains[:, 1])


def test_an_input_that_goes_silent_is_named_with_the_misfit_it_may_cause():
    """Issue #47 item 6: a battery driver that stopped kept its last current in force for good
    (right for a publisher that sends only on change), and when the true current then changed
    the misfit blamed a magnet. The silence is shown in /diagnostics and named with the misfit;
    the input publishing again clears it."""
    from test_session import EXACT, RATE_HZ, distorted

    gain = np.array([10e-6, 0.0, 0.0])  # T/A along x: 3 A puts 30 µT on the sensor
    session = CalibrationSession(
        SessionSettings(interference_inputs=(BATTERY,), use_temperature=False,
                        auto_calibrate=False),
        calibration=EXACT.with_compensation(Compensation((BATTERY,), gain[:, None],
                                                         np.zeros(3))))
    raw, step = distorted('tumble', 2500, seed=45), round(1e9 / RATE_HZ)
    silent_values, warnings = [], []
    for index, row in enumerate(raw):
        stamp, seconds = (index + 1) * step, index / RATE_HZ
        current = 3.0 if seconds < 15.0 else 0.0  # the driver stops at 15 s; the motors too
        if seconds < 15.0 and index % 5 == 0:
            session.process_input(0, stamp, current)
        session.process(stamp, 'imu_link', row + gain * current)
        if index % 50 == 0:
            session.poll()
            warnings += [event.message for event in session.take_events()
                         if event.level == 'warning']
            silent_values.append(session.report().values.get('interference_silent'))
    silent = f"interference input '{BATTERY}' has sent nothing for"
    assert silent_values[:14] == [None] * 14  # publishing at 10 Hz: not silent
    assert silent_values[-1].startswith(silent) and silent_values[-1].endswith(
        'its own field is held at its last value, 3'), silent_values[-1]
    misfits = [message for message in warnings if 'does not fit the live data' in message]
    assert misfits and silent in misfits[0], warnings
    session.process_input(0, (len(raw) + 1) * step, 0.0)
    session.process_input(0, (len(raw) + 2) * step, 0.0)
    assert 'interference_silent' not in session.report().values
