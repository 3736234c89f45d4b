# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Units end to end (issue #21.1): a calibration fitted offline loads in tesla, or is refused.

The node works in tesla. A file ``mag_calibrator_fit`` wrote from a log in microtesla or in raw
counts used to load as if its numbers were tesla (an offset of 222925 counts read as 222925 T);
now the CLI writes tesla (from --units, --scale or a header's unit), a file naming another unit
of magnetic field is converted at load, and one in unknown units is refused with the fix.
"""

import json

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration, CalibrationError
from mag_calibrator_ros.calibration.store.calibration_file import (
    CalibrationFileError,
    calibration_from_parameters,
    calibration_yaml,
    load_calibration,
    read_calibration_file,
    save_calibration,
)
from mag_calibrator_ros.tools.fit import main

FIELD_T = 50e-6
OFFSET_T = np.array([22.0e-6, -31.0e-6, 12.5e-6])
SOFT_IRON = np.array([[1.04, 0.02, 0.0], [0.02, 0.97, 0.01], [0.0, 0.01, 0.99]])
TESLA_PER_COUNT = 0.15e-6  # AK09916 (ICM-20948): 0.15 uT per count


def field_in_tesla(n=800, seed=3):
    """Raw readings of a known field F in every direction, distorted by soft and hard iron."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return FIELD_T * directions @ SOFT_IRON.T + OFFSET_T


def write_rows(path, rows, header=None, fmt='%.6f'):
    np.savetxt(path, rows, fmt=fmt, delimiter=',', header=header or '', comments='')
    return path


def corrected_field_error(calibration, raw_tesla):
    """Largest |corrected| off the true field, in % of it."""
    magnitude = np.linalg.norm(calibration.apply(raw_tesla), axis=1)
    return 100.0 * np.max(np.abs(magnitude / FIELD_T - 1.0))


# --- the CLI writes tesla -------------------------------------------------------------------


@pytest.mark.parametrize('mode', [[], ['--all']])
def test_counts_with_scale_load_in_tesla_within_one_percent(tmp_path, capsys, mode):
    raw = field_in_tesla()
    counts = write_rows(tmp_path / 'counts.csv', np.round(raw / TESLA_PER_COUNT), fmt='%.0f')
    output = tmp_path / 'cal.yaml'
    code = main([str(counts), '--scale', '0.15e-6', '-o', str(output), '--json', *mode])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0, summary['reason']
    assert summary['units'] == 'T'
    assert any('--scale' in note for note in summary['input']['notes'])
    loaded = load_calibration(output, '/mag_calibrator')
    assert loaded.metadata['units'] == 'T'
    np.testing.assert_allclose(loaded.offset, OFFSET_T, atol=0.5e-6)
    assert corrected_field_error(loaded, raw) < 1.0
    assert loaded.field_strength == pytest.approx(FIELD_T, rel=0.01)


def test_microtesla_with_units_is_written_in_tesla(tmp_path, capsys):
    raw = field_in_tesla()
    log = write_rows(tmp_path / 'log.csv', raw * 1e6)
    output = tmp_path / 'cal.yaml'
    code = main([str(log), '--units', 'uT', '-o', str(output), '--json'])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0, summary['reason']
    assert summary['units'] == 'uT'  # the report stays in the log's unit
    loaded = load_calibration(output)
    np.testing.assert_array_equal(loaded.offset, np.array(summary['offset']) * 1e-6)
    assert corrected_field_error(loaded, raw) < 1.0


def test_a_header_unit_is_reported_and_applied(tmp_path, capsys):
    raw = field_in_tesla()
    header = 'Time (s),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT)'
    rows = np.column_stack([np.arange(len(raw)) * 0.01, raw * 1e6])
    log = write_rows(tmp_path / 'phone.csv', rows, header=header)
    output = tmp_path / 'cal.yaml'
    assert main([str(log), '-o', str(output)]) == 0
    out = capsys.readouterr().out
    assert 'units uT' in out and 'units uT from the header' in out
    assert corrected_field_error(load_calibration(output), raw) < 1.0
    # a different --units contradicts the header: refused, not guessed
    assert main([str(log), '--units', 'nT']) == 2
    assert "is in 'uT'" in capsys.readouterr().err
    # --scale is for raw counts, not for a log that says its unit
    assert main([str(log), '--scale', '1e-6']) == 2
    assert '--scale is for raw counts' in capsys.readouterr().err


def test_output_without_a_known_unit_is_refused_before_fitting(tmp_path, capsys):
    log = write_rows(tmp_path / 'counts.csv', np.round(field_in_tesla() / TESLA_PER_COUNT),
                     fmt='%.0f')
    output = tmp_path / 'cal.yaml'
    for extra in ([], ['--units', 'counts']):
        assert main([str(log), *extra, '-o', str(output)]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1
        assert '--units' in err and '--scale' in err and 'tesla' in err
        assert not output.exists()
    assert main([str(log), '--units', 'counts', '--quiet']) == 0  # a label, without --output


@pytest.mark.parametrize(('argv', 'words'), [
    (['--scale', '0'], ('--scale', 'positive')),
    (['--scale', 'nan'], ('--scale',)),
    (['--scale', '1e-7', '--units', 'uT'], ('--scale', '--units uT')),
    (['--output', ''], ('--output', 'empty')),
    (['--plot', ''], ('--plot', 'empty')),
])
def test_bad_unit_and_output_options(tmp_path, capsys, argv, words):
    log = write_rows(tmp_path / 'log.csv', field_in_tesla() * 1e6)
    assert main([str(log), *argv]) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert len(captured.err.splitlines()) == 1
    for word in words:
        assert word in captured.err


def test_scale_converts_full_scale_and_field_strength_given_in_counts(tmp_path, capsys):
    raw = field_in_tesla()
    counts = write_rows(tmp_path / 'counts.csv', np.round(raw / TESLA_PER_COUNT), fmt='%.0f')
    code = main([str(counts), '--scale', '0.15e-6', '--field-strength', '400', '--full-scale',
                 '32752', '--json'])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0, summary['reason']
    assert summary['field_strength'] == pytest.approx(400 * 0.15e-6)
    assert summary['rejects']['saturated'] == 0


# --- the file: converted at load, or refused ---------------------------------------------------


def calibration_in(units, factor):
    """The calibration written in ``units`` (``factor`` tesla each), labelled so."""
    return Calibration(OFFSET_T / factor, SOFT_IRON, FIELD_T / factor, 'full',
                       {'units': units, 'samples': 100})


@pytest.mark.parametrize(('units', 'factor'), [
    ('uT', 1e-6), ('µT', 1e-6), ('nT', 1e-9), ('G', 1e-4), ('gauss', 1e-4), ('mG', 1e-7),
    ('T', 1.0),
])
def test_a_file_in_another_unit_loads_in_tesla_and_says_so(tmp_path, units, factor):
    path = tmp_path / 'cal.yaml'
    path.write_text(calibration_yaml(calibration_in(units, factor), '/**'))
    loaded = read_calibration_file(path)
    calibration = loaded.calibration
    np.testing.assert_allclose(calibration.offset, OFFSET_T, rtol=1e-12)
    np.testing.assert_array_equal(calibration.matrix, SOFT_IRON)  # M does not scale
    assert calibration.field_strength == pytest.approx(FIELD_T, rel=1e-12)
    assert calibration.metadata['units'] == 'T'
    assert calibration.metadata['samples'] == 100
    converted = [note for note in loaded.notes if 'converted' in note]
    assert bool(converted) == (units != 'T')
    if converted:
        assert units in converted[0] and 'tesla' in converted[0]


def test_the_old_cli_file_in_microtesla_loads_within_one_percent(tmp_path):
    """What mag_calibrator_fit wrote before: numbers in uT labelled units "uT"."""
    raw = field_in_tesla()
    path = tmp_path / 'cal.yaml'
    calibration = Calibration(OFFSET_T * 1e6, np.linalg.inv(SOFT_IRON), FIELD_T * 1e6, 'full',
                              {'units': 'uT'})
    path.write_text(calibration_yaml(calibration, '/**'))
    assert corrected_field_error(load_calibration(path), raw) < 1e-6


@pytest.mark.parametrize('units', ['input', 'counts', '', 5, True])
def test_unknown_units_are_refused_at_load_naming_the_fix(tmp_path, units):
    path = tmp_path / 'cal.yaml'
    text = calibration_yaml(calibration_in('T', 1.0), '/**').replace(
        'units: "T"', f'units: {json.dumps(units)}')
    assert f'units: {json.dumps(units)}' in text
    path.write_text(text)
    with pytest.raises(CalibrationFileError) as error:
        load_calibration(path)
    message = str(error.value)
    assert 'cal.yaml' in message and 'calibration.units' in message
    assert '--units' in message and '--scale' in message
    with pytest.raises(CalibrationFileError, match='cannot save'):  # never written either
        save_calibration(tmp_path / 'new.yaml', calibration_in('input', 1e-6))
    assert not (tmp_path / 'new.yaml').exists()


def test_params_file_values_convert_or_refuse_as_the_file_does():
    """The node's --params-file path: calibration.* parameters, metadata with the units."""
    converted = calibration_from_parameters(OFFSET_T * 1e6, SOFT_IRON, FIELD_T * 1e6, 'full',
                                            {'units': 'uT'})
    np.testing.assert_allclose(converted.offset, OFFSET_T, rtol=1e-15)
    assert converted.field_strength == pytest.approx(FIELD_T, rel=1e-15)
    assert converted.metadata['units'] == 'T'
    with pytest.raises(CalibrationError, match='--scale'):
        calibration_from_parameters(OFFSET_T, SOFT_IRON, FIELD_T, 'full', {'units': 'input'})
    kept = calibration_from_parameters(OFFSET_T, SOFT_IRON, FIELD_T, 'full', {})
    np.testing.assert_array_equal(kept.offset, OFFSET_T)


@pytest.mark.parametrize(('units', 'noted'), [('uT', False), ('mG', True)])
def test_a_stated_unit_that_makes_the_field_unlike_the_earths_is_named(shared_data, capsys,
                                                                       units, noted):
    """fxos8700's log is in µT (53 µT): --units mG makes it 5.3 µT, said on the answer (issue
    #46); in gauss (5.3 mT) the readings are refused outright (test_fit_cli.py)."""
    log = shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'
    status = main([str(log), '--units', units, '--json'])
    summary = json.loads(capsys.readouterr().out)
    notes = [note for note in summary['input']['notes'] if note.startswith('--units')]
    assert bool(notes) == noted, notes
    if noted:
        assert 'outside 10-100 µT' in notes[0] and units in notes[0]
    assert status in (0, 1)
