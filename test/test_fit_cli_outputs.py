# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_fit's output files and dates as users give them (issue #22.11): the path
printed is the file written, a plot that cannot be written is an error (exit 2) and leaves no
partial image, an empty --output is refused, and a date before the model says so."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mag_calibrator_ros.tools.fit import main

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
PORTLAND = ['--latitude', '45.5', '--longitude', '-122.7']


@pytest.fixture
def log(tmp_path):
    rng = np.random.default_rng(11)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    path = tmp_path / 'log.csv'
    np.savetxt(path, 50.0 * directions + [12.0, -4.0, 30.0], fmt='%.4f', delimiter=',')
    return path


def one_line_error(capsys, argv, *words):
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2
    assert captured.out == ''
    assert len(captured.err.splitlines()) == 1, captured.err
    for word in words:
        assert word in captured.err
    return captured.err


def test_plot_without_a_suffix_reports_the_file_it_wrote(log, tmp_path, capsys):
    plot = tmp_path / 'outdir'
    code = main([str(log), '--plot', str(plot), '--json'])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0
    written = tmp_path / 'outdir.png'
    assert summary['outputs']['plot'] == str(written)
    assert written.read_bytes().startswith(PNG_MAGIC)
    assert not plot.exists()
    main([str(log), '--plot', str(plot)])
    assert f'plot      {written}' in capsys.readouterr().out


def test_plot_to_a_device_is_refused_with_exit_2(log, capsys, never_written):
    one_line_error(capsys, [str(log), '--plot', '/dev/full'], '/dev/full', 'plot',
                   'character device')


def test_plot_onto_a_directory_is_refused_and_leaves_it(log, tmp_path, capsys):
    folder = tmp_path / 'plots.png'
    folder.mkdir()
    one_line_error(capsys, [str(log), '--plot', str(folder)], 'plots.png', 'plot')
    assert folder.is_dir() and not list(folder.iterdir())


def test_a_failed_plot_leaves_the_previous_file_and_no_partial_one(log, tmp_path, capsys,
                                                                    monkeypatch):
    plot = tmp_path / 'mag.png'
    plot.write_bytes(b'previous plot')

    def fail_half_way(descriptor, data):
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr('mag_calibrator_ros.calibration.store.safe_file.os.write', fail_half_way)
    one_line_error(capsys, [str(log), '--plot', str(plot)], 'mag.png', 'No space left')
    assert plot.read_bytes() == b'previous plot'
    assert sorted(path.name for path in tmp_path.iterdir()) == ['log.csv', 'mag.png']


def test_an_unknown_plot_format_is_a_usage_error(log, tmp_path, capsys):
    one_line_error(capsys, [str(log), '--plot', str(tmp_path / 'mag.xyz')], 'mag.xyz')
    assert not (tmp_path / 'mag.xyz').exists()


@pytest.mark.parametrize('option', ['--output', '-o', '--plot'])
@pytest.mark.parametrize('value', ['', '  '])
def test_an_empty_output_name_is_refused(log, capsys, option, value):
    one_line_error(capsys, [str(log), '--units', 'uT', option, value], 'empty')


def test_a_date_before_the_model_says_so(log, capsys):
    error = one_line_error(capsys, [str(log), *PORTLAND, '--date', '2019-06-01'],
                           '2019-06-01', 'before')
    assert 'newer model' not in error
    one_line_error(capsys, [str(log), *PORTLAND, '--date', '2035-01-01'], 'newer model')


# --- a reader that stops early ---------------------------------------------------------------


@pytest.mark.parametrize('reader', ['true', 'head -c 0'])
def test_output_into_a_closed_pipe_exits_quietly(log, tmp_path, reader):
    """``--json | head``: a reader that stops (here before the summary comes) ends the run as
    Unix tools end, without a BrokenPipeError traceback; the exit status is the fit's."""
    script = tmp_path / 'fit.py'
    script.write_text('import sys\nfrom mag_calibrator_ros.tools.fit import main\n'
                      f'sys.exit(main([{str(log)!r}, "--json"]))\n')
    pipeline = subprocess.run(
        f'"{sys.executable}" "{script}" | {reader}; exit "${{PIPESTATUS[0]}}"',
        shell=True, executable='/bin/bash', capture_output=True, text=True, timeout=120,
        check=False)
    assert pipeline.stderr == ''
    assert pipeline.returncode == 0
