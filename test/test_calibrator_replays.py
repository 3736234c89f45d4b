# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What the calibrator node decides over DDS, replayed without ROS (issue #43): the simulated
board the driver node publishes (sim.board.BoardModel) streamed with its stamps through a
CalibrationSession, as the node streams imu/mag and imu/data_raw. The session decides from
stamps only, so each replay takes the node's decisions in a fraction of a second; the node's
wiring stays in the DDS tests (test_calibrator_node*.py)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pytest
from test_alignment_wait import tumble_then_poses

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.earth_field import earth_field
from mag_calibrator_ros.calibration.live.offline import calibrate_now
from mag_calibrator_ros.calibration.live.report import CalibrationAttempt, SessionReport
from mag_calibrator_ros.calibration.live.session import (
    CalibrationSession,
    Processed,
    SessionEvent,
)
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig

RATE_HZ = 100.0  # the driver's rate_hz in the DDS tests
STEP_NS = 10_000_000
FRAME = 'imu_link'
HARD_IRON_UT = (120.0, -80.0, 60.0)
SOFT_IRON = (1.15, 0.10, -0.08, 0.10, 0.85, 0.12, -0.08, 0.12, 1.00)  # strong, symmetric
FIELD_T = 50e-6  # the simulated field's strength without a location
BERLIN = (52.52, 13.40, 34.0)
MISALIGNMENT_DEG = (1.8, -1.9, 1.4)  # 3.0 deg


def board_stream(seconds: float, **config) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                    BoardModel]:
    """(mag T, accel m/s^2, gyro rad/s) rows at RATE_HZ of a simulated board configured as
    the driver's ``sim.*`` parameters configure it, and the board (its truth)."""
    board = BoardModel(SimConfig(**config))
    return (*board_readings(board, seconds, RATE_HZ), board)


@dataclass
class Replay:
    """A session fed message by message, as the node feeds it: each magnetometer reading after
    the IMU sample taken with it, a poll after each (the node's poll timer), and a report with
    ``now`` once a stream second (the node's diagnostics tick)."""

    session: CalibrationSession
    outputs: list[Processed] = field(default_factory=list)
    events: list[SessionEvent] = field(default_factory=list)
    reports: list[SessionReport] = field(default_factory=list)
    adopted: list[tuple[int, Calibration]] = field(default_factory=list)
    """(index of the message after which, calibration) for each calibration put in force."""
    corrected: int = 0
    """Messages corrected (what the node publishes on imu/mag_corrected)."""

    def run(self, mag: np.ndarray, accel: np.ndarray | None = None,
            gyro: np.ndarray | None = None,
            until: Callable[[Replay], bool] | None = None) -> Replay:
        start = len(self.outputs)
        for offset, row in enumerate(mag):
            index = start + offset
            stamp = index * STEP_NS
            if accel is not None:
                self.session.process_imu(stamp, FRAME, accel[offset],
                                         None if gyro is None else gyro[offset])
            self.outputs.append(self.session.process(stamp, FRAME, row))
            self.corrected += self.outputs[-1].corrected is not None
            self.session.poll()
            taken = self.session.take_events()
            self.events += taken
            if any(event.adopted for event in taken):
                self.adopted.append((index, self.session.calibration))
            if index % int(RATE_HZ) == 0:
                self.reports.append(self.session.report(index / RATE_HZ))
            if until is not None and until(self):
                break
        return self

    def messages(self, level: str) -> list[str]:
        return [event.message for event in self.events if event.level == level]


def in_force_and_after(count: int) -> Callable[[Replay], bool]:
    """Until a calibration went in force and ``count`` messages came after it."""
    return lambda replay: bool(replay.adopted) and (
        len(replay.outputs) - 1 - replay.adopted[0][0] >= count)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(min(1.0, max(-1.0, cosine)))))


# -- calibrating by itself (test_calibrator_node.py's auto node, its two robots) -----------------


@pytest.fixture(scope='module')
def tumbled():
    """The DDS module's live board (strong hard and soft iron, tumbled, seed 3) as the auto
    calibrator (``auto_calibrate_period`` 1 s) takes it, until 3 s after it calibrated. Without
    its IMU: a tumble is never still, so with one the first calibration would only wait longer,
    for the alignment's bound (test_alignment_wait.py)."""
    mag, _, _, _ = board_stream(
        20.0, hard_iron_ut=HARD_IRON_UT, soft_iron=SOFT_IRON, noise_ut=0.05, motion='tumble',
        seed=3)
    session = CalibrationSession(SessionSettings(auto_calibrate_period=1.0))
    return Replay(session).run(mag, until=in_force_and_after(300))


def test_a_tumbled_board_is_calibrated_by_itself_to_its_hard_iron(tumbled):
    """test_calibrator_node.py's auto node: calibrated by itself (its adoption is what
    auto_save writes), the offset the board's hard iron."""
    replay = tumbled
    report = replay.session.report()
    assert report.state.startswith('calibrated'), report.progress
    assert report.last_attempt is not None and report.last_attempt.success
    assert report.counts.adoptions.get('auto') == 1
    ((_, calibration),) = replay.adopted
    assert calibration is replay.session.calibration
    assert any(event.adopted for event in replay.events)  # what the node auto-saves on
    np.testing.assert_allclose(calibration.offset, np.array(HARD_IRON_UT) * 1e-6, atol=2e-6)
    assert calibration.metadata['frame_id'] == FRAME


def test_the_fit_decisions_are_said_at_debug_level(tumbled):
    """What ``--log-level mag_calibrator:=debug`` shows (test_calibrator_node_first_day.py):
    why no automatic calibration was tried yet, and the judgement of the one in force."""
    replay = tumbled
    debug = replay.messages('debug')
    assert any('automatic calibration not tried yet' in line for line in debug), debug[:5]
    assert any(line.startswith('calibration in force') for line in debug), debug[-5:]
    info = replay.messages('info')
    assert not any('not tried yet' in line or line.startswith('calibration in force')
                   for line in info)


@pytest.mark.parametrize('hard_iron', [(120.0, -80.0, 60.0), (-40.0, 150.0, 20.0)],
                         ids=['robot1', 'robot2'])
def test_each_robots_board_is_calibrated_in_3d_by_itself(hard_iron):
    """The two robots of test_calibrator_node.py (each its own hard iron, seed 7, no IMU): a
    3-D calibration by itself (a tumble that starts with a full turn about one axis may be
    calibrated planar first, issue #13), its offset that robot's, stamped with the frame."""
    mag, _, _, _ = board_stream(30.0, hard_iron_ut=hard_iron, motion='tumble', seed=7)
    replay = Replay(CalibrationSession()).run(
        mag, until=lambda r: r.session.calibration is not None
        and r.session.calibration.model != 'planar')
    calibration = replay.session.calibration
    assert calibration is not None and calibration.model != 'planar', replay.reports[-1].progress
    assert replay.session.report().counts.adoptions.get('auto', 0) >= 1
    np.testing.assert_allclose(calibration.offset, np.array(hard_iron) * 1e-6, atol=3e-6)
    assert calibration.metadata['frame_id'] == FRAME


# -- ~/calibrate refused (test_calibrator_node.py) -----------------------------------------------


def requested(motion: str, seconds: float, fill: int) -> tuple[Replay, CalibrationAttempt,
                                                              list[SessionEvent]]:
    """``seconds`` of the board moved by ``motion`` (the buffer then holds ``fill`` samples at
    least), then a fit asked for (``~/calibrate``), with ``model: full`` and ``auto_calibrate:
    false``."""
    mag, _, _, _ = board_stream(seconds, hard_iron_ut=HARD_IRON_UT, motion=motion)
    session = CalibrationSession(SessionSettings(auto_calibrate=False, model='full'))
    replay = Replay(session).run(mag)
    assert session.report().buffer.fill >= fill
    taken: list[SessionEvent] = []
    return replay, calibrate_now(session, events=taken), taken


def test_too_little_coverage_is_refused_with_a_reason():
    replay, attempt, _ = requested('still', 1.0, 20)
    assert not attempt.success
    assert len(attempt.message) > 20, attempt.message
    assert replay.session.calibration is None
    assert all(output.corrected is None for output in replay.outputs)  # nothing published


def test_planar_motion_with_a_3d_model_is_refused():
    replay, attempt, taken = requested('yaw', 3.0, 60)
    assert not attempt.success, attempt.message
    assert attempt.message.startswith('calibration failed: ')
    assert 'near one plane' in attempt.message  # a turn in place: a circle, not a sphere
    assert [event.attempt for event in taken if event.attempt is not None] == [attempt]
    assert replay.session.report().state == 'collecting'
    assert replay.session.calibration is None


# -- a calibration judged not to fit (test_calibrator_node_first_day.py) -------------------------


def other_boards_calibration() -> Calibration:
    """Another board's file: its offset 150 uT away from this one's."""
    soft = np.array(SOFT_IRON).reshape(3, 3)
    return Calibration(np.array(HARD_IRON_UT) * 1e-6 + [140e-6, -60e-6, 20e-6],
                       np.linalg.inv(soft), FIELD_T, 'full',
                       {'residual_rms_pct': 0.5, 'coverage': 0.9})


def test_a_calibration_judged_not_to_fit_is_marked_with_its_uncertainty_until_recalibrated():
    """Every corrected reading carries its 1-sigma (the node puts its square on the covariance:
    test_calibrator_node_first_day.py). Another board's file is off by ~150 uT: from the first
    message, before anything is judged, each reading off by more than half the field has an
    error inside the 99.7 % ellipsoid of its covariance (issue #45: 681 messages had none);
    the misfit sizes it by the measured error until the recalibration, and then it shrinks to
    what the new calibration is off by."""
    mag, accel, gyro, _ = board_stream(
        40.0, hard_iron_ut=HARD_IRON_UT, soft_iron=SOFT_IRON, noise_ut=0.05, motion='tumble',
        seed=5)
    truth = (mag - np.array(HARD_IRON_UT) * 1e-6) @ np.linalg.inv(
        np.array(SOFT_IRON).reshape(3, 3)).T
    # the misfit's path: with the gyroscope's fit a step re-learns the offset first
    # (test_gyro_aided.py::test_another_boards_file_is_corrected_by_a_step_within_seconds)
    session = CalibrationSession(SessionSettings(gyro_aided=False))
    session.apply_calibration(other_boards_calibration(), 'file')
    assert session.report().counts.adoptions == {'file': 1}
    replay = Replay(session).run(mag, accel, gyro, until=in_force_and_after(200))
    assert session.report().counts.adoptions.get('auto', 0) >= 1, session.report().state
    outputs = replay.outputs
    assert all(output.uncertainty > 0.0 for output in outputs)  # never "unknown"
    errors = np.array([np.linalg.norm(output.corrected - truth[index])
                       for index, output in enumerate(outputs)])
    sigmas = np.array([output.uncertainty for output in outputs])
    off = errors > 0.5 * FIELD_T
    assert off[0] and off.sum() > 50  # the wrong file, in force from the first message
    chi2_3dof_997 = 14.16
    assert np.all(errors[off] ** 2 <= chi2_3dof_997 * sigmas[off] ** 2), (
        np.max(errors[off] / sigmas[off]))
    adopted = replay.adopted[0][0]
    after = slice(adopted + 100, None)  # the new calibration's window has filled
    assert len(errors[after]) >= 50 and np.all(errors[after] < 0.1 * FIELD_T)  # recalibrated
    assert np.all(sigmas[after] < 0.05 * FIELD_T)  # and says so
    assert np.median(sigmas[after]) < 0.1 * np.median(sigmas[off])
    # /diagnostics' status says the same: unreliable under the wrong file, trusted after
    before = [report for index, report in enumerate(replay.reports)
              if index * RATE_HZ < adopted]
    assert before and all(report.values['calibration_status'] == 'unreliable'
                          for report in before[1:])
    final = session.report()  # no dip known here (a tumble is never still): at best 'low'
    assert final.accuracy.status == 'low' and final.accuracy.direction_sigma_deg < 0.5, (
        final.accuracy)
    assert final.values['calibration_status'] == final.accuracy.status


# -- with an IMU (test_calibrator_node_aligned_first.py, test_calibrator_node_imu.py) ------------


def test_the_first_corrected_reading_is_aligned_to_the_imu():
    """The first automatic calibration waits for still tilts (said on /diagnostics), so the
    corrected field is in the IMU frame from its first message: a magnetometer 3 deg off the
    accelerometer, tumbled (coverage, never still), then held still at one tilt after another."""
    mag, accel, gyro, misalignment = tumble_then_poses(12.0, 45.0)
    truth = (mag - np.array(HARD_IRON_UT) * 1e-6) @ misalignment.T  # the field, IMU frame
    # the sphere's rule: the gyroscope's own fit (it aligns without tilts) is another test's
    replay = Replay(CalibrationSession(SessionSettings(gyro_aided=False))).run(
        mag, accel, gyro, until=lambda r: r.corrected >= 50)
    corrected = [(index, output.corrected) for index, output in enumerate(replay.outputs)
                 if output.corrected is not None]
    assert len(corrected) >= 50, replay.reports[-1].progress
    first = corrected[0][0]
    assert first / RATE_HZ > 12.0  # ready while tumbling, held back until aligned
    errors = [angle_deg(vector, truth[index]) for index, vector in corrected[:50]]
    assert np.sqrt(np.mean(np.square(errors))) < 1.0  # unaligned: 3 deg
    assert any('waiting for still tilts' in report.message for report in replay.reports)
    assert replay.session.report().counts.adoptions.get('auto') == 1


def test_a_misaligned_board_held_at_tilts_is_aligned_and_checked_against_the_model():
    """test_calibrator_node_imu.py's board (3 deg off its IMU, held at one tilt after another,
    in Berlin), the calibrator told the World Magnetic Model there: ~/calibrate once ten still
    attitudes and half the directions are in, aligned to the IMU and sized by the model."""
    mag, accel, gyro, board = board_stream(
        60.0, hard_iron_ut=HARD_IRON_UT, soft_iron=SOFT_IRON, noise_ut=0.3, motion='poses',
        seed=4, mag_misalignment_deg=MISALIGNMENT_DEG, latitude=BERLIN[0],
        longitude=BERLIN[1], altitude_m=BERLIN[2])
    model = earth_field(*BERLIN)
    session = CalibrationSession(SessionSettings(auto_calibrate=False, min_coverage=0.45))
    session.set_earth_field(model)

    def ready(replay: Replay) -> bool:
        if len(replay.outputs) % int(RATE_HZ):  # looked at once a stream second
            return False
        report = replay.session.report(measure_coverage=True)
        return report.imu.static_attitudes >= 10 and report.coverage.fraction >= 0.5

    replay = Replay(session).run(mag, accel, gyro, until=ready)
    report = session.report(measure_coverage=True)
    assert ready(replay), (report.progress, report.imu.static_attitudes)
    attempt = calibrate_now(session)
    assert attempt.success, attempt.message
    assert 'aligned to the IMU' in attempt.message
    assert 'WMM2025' in attempt.message and 'declination' in attempt.message
    assert 'accuracy high: heading sigma' in attempt.message  # ~/calibrate's answer
    assert 'deg (measured)' in attempt.message
    calibration = session.calibration
    assert rotation_angle_deg(calibration.rotation @ board.mag_misalignment.T) < 0.3
    assert calibration.field_strength == pytest.approx(model.intensity_nt * 1e-9)
    assert calibration.metadata['dip_deg'] == pytest.approx(model.inclination_deg, abs=0.3)
    report = session.report()
    assert report.imu.paired > 0.9 * report.counts.accepted
    assert report.values['heading_dip_source'] == 'measured'
    assert 0.0 < report.values['heading_sigma_deg'] < 2.0
    # The corrected stream is the true field in the IMU frame.
    start = len(replay.outputs)
    replay.run(mag[start:start + 50], accel[start:start + 50], gyro[start:start + 50])
    errors = [angle_deg(output.corrected, board.true_field_tesla(index / RATE_HZ))
              for index, output in enumerate(replay.outputs[start:], start)]
    assert len(errors) == 50 and np.sqrt(np.mean(np.square(errors))) < 1.0
    report = session.report(len(replay.outputs) / RATE_HZ)
    values = report.values
    assert report.level == 'OK', report.message
    assert float(values['alignment_angle_deg']) == pytest.approx(3.0, abs=0.3)
    assert 'dip_deg' in values
    assert float(values['declination_deg']) == pytest.approx(model.declination_deg, abs=0.01)
    assert float(values['imu_rate_hz']) > 0.0
