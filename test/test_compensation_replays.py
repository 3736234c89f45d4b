# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field learnt on request, replayed through the session: the course
test_compensation_node.py publishes (a battery current on ``battery_state``, the die
temperature on ``imu/temperature`` every fourth reading, ``imu/mag``), its stamps and values
given to the ``CalibrationSession`` of that test's calibrator as the node's subscriptions give
them. The service wiring and one whole learning over DDS stay in test_compensation_node.py.
"""

from __future__ import annotations

from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.compensation import (
    TEMPERATURE,
    TermReport,
    interference_grade,
    interference_pct,
)
from mag_calibrator_ros.calibration.live.session import CalibrationSession, SessionEvent
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.icm20948 import registers as reg

sys.path.insert(0, str(Path(__file__).parent))
from test_compensation import BATTERY, OFFSET, F, drive  # noqa: E402

RATE_HZ = 20.0  # test_compensation_node.py's course
SECONDS = 100.0


def node_session(**settings) -> CalibrationSession:
    """The session of test_compensation_node.py's calibrator: ``auto_calibrate``, ``refine``
    off, the battery current as its one input, the calibration.* parameters it was given."""
    session = CalibrationSession(SessionSettings(**{
        'auto_calibrate': False, 'refine': False, 'interference_inputs': (BATTERY,),
        'full_scale': reg.MEASUREMENT_LIMIT * reg.TESLA_PER_LSB, **settings}))
    session.apply_calibration(Calibration(OFFSET + np.array([0.8e-6 * 3.0, 0.0, 0.0]),
                                          np.eye(3), F, 'full'), 'parameters')
    return session


def publish(session: CalibrationSession, run: dict[str, np.ndarray], ticket: int | None = None
            ) -> list[SessionEvent]:
    """The course as the node's subscriptions hand it over: each row's battery current, every
    fourth row's temperature, then the reading, all with the row's stamp. With a ``ticket``,
    until its answer came (checked once a second of stream): the events with that ticket."""
    answers = []
    for index, when in enumerate(run['t']):
        stamp = round(float(when) * 1e9)
        session.process_input(0, stamp, float(run['current'][index]))
        if index % 4 == 0:
            session.process_temperature(stamp, float(run['temperature'][index]))
        session.process(stamp, 'imu_link', run['raw'][index])
        if ticket is not None and index % int(RATE_HZ) == 0:
            answers += [event for event in session.take_events() if event.ticket == ticket]
            if answers:
                break
    return answers


def test_learn_compensation_learns_on_request_with_live_learning_off():
    session = node_session(learn_compensation=False)
    publish(session, drive(seconds=30.0, rate=RATE_HZ))
    report = session.report()
    assert report.counts.accepted == 30.0 * RATE_HZ
    assert report.counts.adoptions.get('compensation', 0) == 0  # nothing learnt unasked
    ticket = session.request_compensation(120.0)  # compensation_timeout
    run = drive(seconds=SECONDS, rate=RATE_HZ)
    run['t'] = run['t'] + 31.0  # the robot drives on
    (answer,) = [event.attempt for event in publish(session, run, ticket)]
    assert answer.success, answer.message
    assert answer.message.startswith('learned in ')
    assert session.calibration.compensation is not None
    assert session.report().counts.adoptions.get('compensation') == 1
    # its size on ArduPilot's compassmot scale: the K in force over the current's 5-95 % range
    low, high = np.percentile(run['current'], [5.0, 95.0])
    gain = np.linalg.norm(session.calibration.compensation.interference[:, 0])
    learned = session.calibration.metadata_number('compensation_interference_pct')
    assert learned == pytest.approx(100.0 * gain * (high - low) / F, rel=0.02)
    assert f"{learned:.1f} % of F (ArduPilot's compassmot scale: fine)" in answer.message
    values = session.report().values  # /diagnostics
    assert values['compensation_interference_pct'] == learned
    assert values['interference_scale'] == 'fine'


@pytest.mark.parametrize(('pct', 'grade'), [(0.0, 'fine'), (30.0, 'fine'),
                                            (30.1, 'grey zone'), (60.0, 'grey zone'),
                                            (60.1, 'too much')])
def test_the_own_field_is_graded_on_ardupilots_compassmot_scale(pct, grade):
    assert interference_grade(pct).startswith(grade)


def test_the_interference_is_the_inputs_field_not_the_temperature_drift():
    terms = tuple(TermReport(name, 1.0, effect, 0.1, 9.0, True, True)
                  for name, effect in (('a', 12.0), ('b', 20.0), (TEMPERATURE, 40.0)))
    assert interference_pct(terms, ('a', 'b', TEMPERATURE)) == pytest.approx(32.0)
    assert interference_pct(terms, ('a',)) == pytest.approx(12.0)
    assert interference_pct(terms, (TEMPERATURE,)) is None
