#!/usr/bin/env python3
# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The live calibrator on a real IMU in a real hand, judged against motion capture (issue #44).

Data: BROAD, Laidig, Weygers and Seel, "BROAD - A Benchmark for Robust Inertial Orientation
Estimation", Data 6(7):72, 2021, doi:10.3390/data6070072; github.com/dlaidig/broad at the commit
pinned in test/data/public_recordings.json; CC BY 4.0. A myon aktos-t (gyroscope rad/s,
accelerometer m/s^2, magnetometer uT) with the optical attitude ``opt_quat`` (w, x, y, z, IMU to
ENU). Only the development trials are read (``TRIALS``); the others are kept apart to judge the
result on motions it was not tuned on: this bench never loads them.

Each trial is replayed causally through ``CalibrationSession`` (default ``SessionSettings``, the
input's unit µT stamped as ``mag_calibrator_fit`` does), gyroscope and accelerometer through
``process_imu`` and the field through ``process`` in stamp order at BROAD's rate, the inline
runner, ``poll`` as the node's timer. What it publishes is kept per sample: the raw field before
a calibration is in force, the corrected one after. Then, per trial:

- when the first calibration went in force, from the first ``movement`` sample, and its model;
- heading RMS from the motion capture, over the movement samples with optical data: the heading
  of ``R_opt(t - LAG) field(t)`` against north (ENU: 90 deg), the magnetometer lagging the
  optical attitude by ``LAG`` samples; raw, the session's output, and both after its first
  calibration only;
- x-io Fusion (``imufusion``, ENU convention) fed gyroscope, accelerometer and each field, its
  heading error by BROAD's own metric (``heading_error``) RMS over the movement samples;
- the peers given the same samples, batch over the whole trial: the package's ellipsoid fit
  (``fit_calibration``, model 'full', one row per place) and MAGYC's four methods (CoMPAS Lab, PyPI
  ``magyc``, run by benchmarks/peers/magyc_broad.py in a venv of its own; n/a without it).
  MAGYC differentiates the field between successive rows, and the aktos-t holds its
  magnetometer between updates (repeated rows): ``--magyc-step N`` gives it every N-th row,
  its calibration applied to every row;
- the heading sigma it publishes (issue #45): per corrected sample ``heading_sigma_deg`` of its
  ``Processed.uncertainty`` at the dip its report states once a second (as /diagnostics), and
  the share of movement samples whose mocap heading error lies within it and twice it: as
  measured, and with the trial's mean heading error removed (the optical frame's north is not
  magnetic north, and the aktos-t's heading holds a per-trial offset raw: what no calibration
  of the magnetometer can see); the statuses its reports gave;
- the IMU warnings the session logged (warnings naming the accelerometer or gyroscope) and the
  coverage its report reached.

    make fetch-recordings   # once: the trials, outside the repository
    python3.11 -m venv .venv-magyc && .venv-magyc/bin/pip install magyc==1.0.0   # optional
    python benchmarks/bench_broad.py [--dir DIR] [--json out/bench_broad.json] [--magyc-step N]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import subprocess
import sys
import time

import imufusion
import numpy as np
import scipy.io as spio

from mag_calibrator_ros.calibration.fit.coverage import places
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration
from mag_calibrator_ros.calibration.live.error_model import heading_sigma_deg
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'scripts'))
from fetch_public_recordings import recordings_dir  # noqa: E402

TRIALS = (
    '01_undisturbed_slow_rotation_A', '02_undisturbed_slow_rotation_B',
    '03_undisturbed_slow_rotation_C', '04_undisturbed_slow_rotation_with_breaks_A',
    '05_undisturbed_slow_rotation_with_breaks_B', '28_disturbed_stationary_magnet_A',
    '32_disturbed_attached_magnet_1cm',
)
"""BROAD's development set, the only trials this bench reads (issue #44)."""
LAG = 4
"""Samples the aktos-t magnetometer lags the optical attitude by."""
NORTH_DEG = 90.0
"""The heading of north in ENU, atan2(y, x)."""
G = 9.81
POLL_EVERY = 32
EVENTS_EVERY = 512
MAGYC = ('magyc_ls', 'magyc_nls', 'magyc_bfg', 'magyc_ifg')
MAGYC_PYTHON = ROOT / '.venv-magyc' / 'bin' / 'python'
IMU_WORDS = ('accelerometer', 'gyroscope')


def load(path: Path) -> dict:
    data = spio.loadmat(path)
    out = {k: np.ascontiguousarray(data[k], dtype=float)
           for k in ('imu_gyr', 'imu_acc', 'imu_mag', 'opt_quat')}
    out['movement'] = np.asarray(data['movement']).squeeze().astype(bool)
    out['rate'] = float(np.squeeze(data['sampling_rate']))
    return out


def rotate(quat: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Each row of ``vectors`` rotated by its unit quaternion (w, x, y, z), body to world."""
    quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    w, u = quat[:, :1], quat[:, 1:]
    t = 2.0 * np.cross(u, vectors)
    return vectors + w * t + np.cross(u, t)


def mocap_heading_errors(opt_quat: np.ndarray, field: np.ndarray) -> np.ndarray:
    """Heading of the world-frame field minus north, deg in (-180, 180]; NaN without optics."""
    shifted = np.full_like(opt_quat, np.nan)
    shifted[LAG:] = opt_quat[:-LAG]  # the field at t was measured in the attitude of t - LAG
    world = rotate(shifted, field)
    error = np.degrees(np.arctan2(world[:, 1], world[:, 0])) - NORTH_DEG
    return (error + 180.0) % 360.0 - 180.0


def heading_error(imu_quat: np.ndarray, opt_quat: np.ndarray) -> np.ndarray:
    """BROAD's heading error, deg: a reimplementation of example_code/broad_utils.py
    ``calculateErrorQuatEarth`` (q_imu * inv(q_opt), both normalised: the error in the earth
    frame) and ``calculateHeadingError`` (2 atan |z / w| of it), MIT OR CC-BY-4.0, D. Laidig."""
    a = imu_quat / np.linalg.norm(imu_quat, axis=1, keepdims=True)
    b = opt_quat / np.linalg.norm(opt_quat, axis=1, keepdims=True) * [1.0, -1.0, -1.0, -1.0]
    w = a[:, 0] * b[:, 0] - a[:, 1] * b[:, 1] - a[:, 2] * b[:, 2] - a[:, 3] * b[:, 3]
    z = a[:, 0] * b[:, 3] + a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1] + a[:, 3] * b[:, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.degrees(2.0 * np.arctan(np.abs(z / w)))


def fusion(data: dict, field: np.ndarray) -> np.ndarray:
    """x-io Fusion's attitude (w, x, y, z, IMU to ENU) per sample, default gains."""
    settings = imufusion.AhrsSettings()
    settings.convention = imufusion.CONVENTION_ENU
    settings.sample_rate = data['rate']
    ahrs = imufusion.Ahrs()
    ahrs.set_settings(settings)
    gyro, accel = np.degrees(data['imu_gyr']), data['imu_acc'] / G
    out = np.empty((len(field), 4))
    last = field[int(np.argmax(np.all(np.isfinite(field), axis=1)))]
    for i in range(len(field)):
        if np.all(np.isfinite(field[i])):  # a refused reading: the last one published
            last = field[i]
        ahrs.update(gyro[i], accel[i], last)
        out[i] = ahrs.get_quaternion()
    return out


def rms(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values ** 2))) if len(values) else None


def replay(data: dict) -> dict:
    """The trial through the session's face as the node would see it; what it published."""
    session = CalibrationSession(SessionSettings(), metadata={'units': 'uT'})
    step = 1e9 / data['rate']
    published = np.full_like(data['imu_mag'], np.nan)
    sigma = np.full(len(published), np.nan)  # heading 1-sigma, deg, per corrected sample
    statuses: dict[str, int] = {}
    dip = None
    in_force: list[tuple[int, str]] = []  # (sample, model) at each change of calibration
    events: list[tuple[int, str, str, bool]] = []
    current = None
    acc, gyr = data['imu_acc'].tolist(), data['imu_gyr'].tolist()
    start = time.monotonic()
    for i, row in enumerate(data['imu_mag'].tolist()):
        stamp = round(i * step)
        session.process_imu(stamp, '', acc[i], gyr[i])
        processed = session.process(stamp, '', row)
        if processed.accepted:
            published[i] = row if processed.corrected is None else processed.corrected
        if i % round(data['rate']) == 0:  # once a second, as the node's diagnostics
            accuracy = session.report().accuracy
            statuses[accuracy.status] = statuses.get(accuracy.status, 0) + 1
            dip = accuracy.dip_deg
        if processed.corrected is not None and dip is not None:
            sigma[i] = heading_sigma_deg(processed.uncertainty,
                                         processed.calibration.field_strength, dip)
        if processed.calibration is not None and processed.calibration is not current:
            current = processed.calibration
            in_force.append((i, current.model))
        if i % POLL_EVERY == 0:
            session.poll()
        if i % EVENTS_EVERY == 0:
            events += [(i, e.level, e.message, e.adopted) for e in session.take_events()]
    session.finish()
    session.poll()
    events += [(len(published), e.level, e.message, e.adopted) for e in session.take_events()]
    report = session.report()
    warnings = [e for e in events  # the IMU's, not the gyro-aided fit's news
                if e[1] == 'warning' and any(w in e[2].lower() for w in IMU_WORDS)]
    return {
        'published': published, 'in_force': in_force, 'events': events, 'warnings': warnings,
        'heading_sigma': sigma, 'statuses': statuses,
        'coverage': report.coverage.fraction, 'state': report.state,
        'replay_s': time.monotonic() - start,
    }


def ellipsoid(data: dict) -> tuple[np.ndarray | None, str]:
    """The package's ellipsoid fit, model 'full', of the raw rows one per place (as
    ``mag_calibrator_fit --all`` fits them: pauses weigh as moves), applied to every row."""
    result = fit_calibration(places(data['imu_mag'])[0], FitOptions(model='full'))
    if result.calibration is None:
        return None, result.reason
    return result.calibration.apply(data['imu_mag']), ('ok' if result.success
                                                       else f'gates failed: {result.reason}')


def magyc_results(args: argparse.Namespace, paths: list[Path]) -> dict:
    """MAGYC's calibrations per trial (peers/magyc_broad.py's JSON), computed when missing."""
    path = args.magyc
    have = json.loads(path.read_text()) if path.exists() else {}
    missing = [p for p in paths if p.stem not in have]
    if missing and MAGYC_PYTHON.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        print(f'MAGYC: {len(missing)} trial(s) through {MAGYC_PYTHON} (minutes)', flush=True)
        subprocess.run([str(MAGYC_PYTHON), str(ROOT / 'benchmarks/peers/magyc_broad.py'),
                        *map(str, missing), '-o', str(path), '--step', str(args.magyc_step)],
                       check=False)
        have = json.loads(path.read_text()) if path.exists() else {}
    elif missing:
        print(f'MAGYC: n/a (no {MAGYC_PYTHON}: python3.11 -m venv .venv-magyc && '
              '.venv-magyc/bin/pip install magyc==1.0.0)', flush=True)
    return have


def magyc_apply(entry: dict, raw: np.ndarray) -> np.ndarray | None:
    """MAGYC's correction, inv(soft_iron) (raw - hard_iron), or None when it gave none."""
    if 'error' in entry or not entry.get('finite', False):
        return None
    soft, hard = np.asarray(entry['soft_iron']), np.asarray(entry['hard_iron'])
    return (raw - hard) @ np.linalg.inv(soft).T


def evaluate(name: str, data: dict, magyc: dict | None) -> dict:
    raw, opt, moving = data['imu_mag'], data['opt_quat'], data['movement']
    rate = data['rate']
    run = replay(data)
    published = run['published']
    first_move = int(np.argmax(moving))
    first_cal = run['in_force'][0][0] if run['in_force'] else None
    sent = np.all(np.isfinite(published), axis=1)
    mask = moving & sent & np.all(np.isfinite(np.roll(opt, LAG, axis=0)), axis=1)
    mask[:LAG] = False
    after = mask.copy()
    after[:len(after) if first_cal is None else first_cal] = False

    def mocap(field: np.ndarray, where: np.ndarray = mask) -> float | None:
        return rms(mocap_heading_errors(opt, field)[where])

    def through_fusion(field: np.ndarray) -> float | None:
        return rms(heading_error(fusion(data, field), opt)[moving])

    fields = {'raw': raw, 'session': published}
    peers: dict[str, dict] = {}
    corrected, status = ellipsoid(data)
    peers['ellipsoid'] = {'status': status}
    if corrected is not None:
        fields['ellipsoid'] = corrected
    for method in MAGYC:
        entry = (magyc or {}).get(name, {}).get('methods', {}).get(method)
        if entry is None:
            peers[method] = {'status': 'n/a'}
            continue
        corrected = magyc_apply(entry, raw)
        peers[method] = {'status': entry.get('error', 'ok' if corrected is not None
                                               else 'not finite'),
                         'seconds': entry.get('seconds'),
                         'step': (magyc or {}).get(name, {}).get('step')}
        if corrected is not None:
            fields[method] = corrected
    heading = {key: mocap(field) for key, field in fields.items()}
    fused = {key: through_fusion(field) for key, field in fields.items()}
    for key in peers:
        peers[key].update(heading_deg=heading.get(key), fusion_deg=fused.get(key))
    messages: dict[str, int] = {}
    errors, sigma = mocap_heading_errors(opt, published), run['heading_sigma']
    scored = mask & np.isfinite(sigma)
    coverage_of_sigma = None
    if scored.any():
        e, s = errors[scored], sigma[scored]
        centred = e - np.mean(e)
        coverage_of_sigma = {
            'scored': int(scored.sum()), 'sigma_median_deg': float(np.median(s)),
            'within_1s': float(np.mean(np.abs(e) <= s)),
            'within_2s': float(np.mean(np.abs(e) <= 2 * s)),
            'centred_within_1s': float(np.mean(np.abs(centred) <= s)),
            'centred_within_2s': float(np.mean(np.abs(centred) <= 2 * s)),
            'centred_rms_deg': float(np.sqrt(np.mean(centred ** 2)))}
    for _, _, text, _ in run['warnings']:
        messages[text[:100]] = messages.get(text[:100], 0) + 1
    return {
        'samples': len(raw), 'duration_s': len(raw) / rate,
        'first_movement_s': first_move / rate,
        'first_calibration_after_movement_s': (None if first_cal is None
                                               else (first_cal - first_move) / rate),
        'first_model': run['in_force'][0][1] if run['in_force'] else None,
        'calibrations': [{'t_s': i / rate, 'model': m} for i, m in run['in_force']],
        'adopted_events': [{'t_s': i / rate, 'message': text}
                           for i, _, text, adopted in run['events'] if adopted],
        'refused': int((~sent).sum()), 'scored_samples': int(mask.sum()),
        'heading_deg': {'raw': heading['raw'], 'session': heading['session']},
        'heading_mean_deg': {key: float(np.nanmean(mocap_heading_errors(opt, f)[mask]))
                             for key, f in fields.items()},
        'heading_after_first_deg': ({'raw': mocap(raw, after),
                                     'session': mocap(published, after)}
                                    if first_cal is not None else None),
        'fusion_heading_deg': {'raw': fused['raw'], 'session': fused['session']},
        'peers': peers,
        'heading_sigma': coverage_of_sigma, 'statuses': run['statuses'],
        'imu_warnings': len(run['warnings']), 'imu_warning_texts': messages,
        'coverage': run['coverage'], 'final_state': run['state'],
        'replay_s': run['replay_s'],
    }


def _f(value: float | None, digits: int = 2) -> str:
    return 'n/a' if value is None or not math.isfinite(value) else f'{value:.{digits}f}'


def print_tables(results: dict) -> None:
    print('\nThe session, causal (heading RMS deg; mocap: R_opt(t - lag) field vs north; '
          'Fusion: BROAD metric)')
    head = (f"{'trial':<6}{'t_cal s':>8} {'model':<8}{'cals':>5}{'mocap raw':>10}"
            f"{'session':>8}{'after raw':>10}{'session':>8}{'Fus raw':>8}{'session':>8}"
            f"{'IMU warn':>9}{'cov %':>6}")
    print(head)
    for name, r in results.items():
        after = r['heading_after_first_deg'] or {}
        print(f"{name[:2]:<6}{_f(r['first_calibration_after_movement_s'], 1):>8} "
              f"{r['first_model'] or 'never':<8}{len(r['calibrations']):>5}"
              f"{_f(r['heading_deg']['raw']):>10}{_f(r['heading_deg']['session']):>8}"
              f"{_f(after.get('raw')):>10}{_f(after.get('session')):>8}"
              f"{_f(r['fusion_heading_deg']['raw']):>8}"
              f"{_f(r['fusion_heading_deg']['session']):>8}"
              f"{r['imu_warnings']:>9}{100.0 * r['coverage']:>6.0f}")
    print('\nThe heading sigma it publishes against the mocap error (within 1 sigma / 2 sigma; '
          "centred: the trial's mean error removed)")
    print(f"{'trial':<6}{'scored':>8}{'median σ°':>10}{'1σ':>6}{'2σ':>6}{'centred 1σ':>11}"
          f"{'2σ':>6}{'RMS°':>6}  statuses")
    for name, r in results.items():
        c = r['heading_sigma']
        told = ', '.join(f'{k} {v}' for k, v in sorted(r['statuses'].items()))
        if c is None:
            print(f'{name[:2]:<6}{0:>8}  {told}')
            continue
        print(f"{name[:2]:<6}{c['scored']:>8}{c['sigma_median_deg']:>10.2f}"
              f"{100 * c['within_1s']:>5.0f}%{100 * c['within_2s']:>5.0f}%"
              f"{100 * c['centred_within_1s']:>10.0f}%{100 * c['centred_within_2s']:>5.0f}%"
              f"{c['centred_rms_deg']:>6.2f}  {told}")
    peers = ('ellipsoid', *MAGYC)
    print('\nPeers, batch over the whole trial (heading RMS deg: mocap / Fusion)')
    print(f"{'trial':<6}{'session':>14}" + ''.join(f'{p:>14}' for p in peers))
    for name, r in results.items():
        cells = [f"{_f(r['heading_deg']['session'])}/{_f(r['fusion_heading_deg']['session'])}"]
        for p in peers:
            peer = r['peers'][p]
            cells.append(f"{_f(peer['heading_deg'])}/{_f(peer['fusion_deg'])}")
        print(f'{name[:2]:<6}' + ''.join(f'{c:>14}' for c in cells))
    for name, r in results.items():
        for p in peers:
            if r['peers'][p]['status'] not in ('ok', 'n/a'):
                print(f"  {name[:2]} {p}: {r['peers'][p]['status'][:120]}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--dir', type=Path, default=recordings_dir(),
                        help='where make fetch-recordings put the trials')
    parser.add_argument('--json', type=Path, default=None, help='write the results here')
    parser.add_argument('--magyc', type=Path, default=None,
                        help="MAGYC's calibrations (made by peers/magyc_broad.py if missing; "
                        'default out/bench_broad_magyc_stepN.json)')
    parser.add_argument('--magyc-step', type=int, default=1,
                        help='MAGYC sees every N-th row (default 1: the same samples)')
    parser.add_argument('--trials', default='',
                        help='comma-separated prefixes of the development trials (default all)')
    args = parser.parse_args()
    chosen = [t for t in TRIALS if not args.trials
              or any(t.startswith(p) for p in args.trials.split(','))]
    paths = [args.dir / f'{t}.mat' for t in chosen]
    absent = [p.name for p in paths if not p.exists()]
    if absent:
        print(f"bench_broad: skipped: {', '.join(absent)} not in {args.dir}; run "
              '`make fetch-recordings` (or give --dir)')
        return 0
    if args.magyc is None:
        args.magyc = ROOT / 'out' / f'bench_broad_magyc_step{args.magyc_step}.json'
    magyc = magyc_results(args, paths)
    results = {}
    for path in paths:
        print(f'{path.stem} ...', flush=True)
        results[path.stem] = evaluate(path.stem, load(path), magyc)
    print_tables(results)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1) + '\n')
        print(f'\nwrote {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
