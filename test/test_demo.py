"""mag_calibrator_demo end to end with a short configuration: exit 0, file and PNG written."""

from mag_calibrator_ros.calibration.store.calibration_file import load_calibration
from mag_calibrator_ros.tools import demo


def test_demo_runs_calibrates_and_writes_outputs(tmp_path, capsys):
    out = tmp_path / 'demo_out'
    status = demo.main(['--output-dir', str(out), '--collect-timeout', '180', '--min-coverage',
                        '0.6', '--evaluate-seconds', '1.5'])
    printed = capsys.readouterr().out
    assert status == 0, printed
    assert (out / 'calibration.png').stat().st_size > 10_000
    calibration = load_calibration(out / 'calibration.yaml')
    assert abs(calibration.field_strength - 50e-6) < 1e-9  # the demo gives the local field
    assert 'direction error' in printed and 'DONE' in printed
    assert 'Alignment to the IMU: rotation' in printed  # the board was held still at tilts
    assert calibration.aligned and calibration.metadata['static_samples'] >= 6


def test_demo_rejects_bad_options(capsys):
    import pytest

    with pytest.raises(SystemExit):
        demo.main(['--evaluate-seconds', '0'])
    with pytest.raises(SystemExit):
        demo.main(['--ground-robot', '--drive-seconds', '500'])  # longer than the course
    assert '--drive-seconds must be within [0, 180]' in capsys.readouterr().err


def test_ground_robot_demo_turns_calibrates_stops_and_scores_the_heading(tmp_path, capsys):
    out = tmp_path / 'ground_out'
    status = demo.main(['--ground-robot', '--output-dir', str(out), '--seed', '2',
                        '--drive-seconds', '25'])
    printed = capsys.readouterr().out
    assert status == 0, printed
    assert 'rotation stopped after' in printed and 'calibrated (model planar' in printed
    assert (out / 'calibration.png').stat().st_size > 10_000
    assert load_calibration(out / 'calibration.yaml').model == 'planar'
    assert 'heading error' in printed and 'DONE' in printed
    # it drove (25 s of the course reach a straight leg at top speed: the full 5 A) with its
    # own field and showed the heading error while driving
    assert 'Its own field' in printed and 'Heading error while driving' in printed
    assert '5.00' in printed.split('Driving 25 s of the ground course')[1]
