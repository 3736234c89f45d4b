# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Safe file access: one path resolution, regular files only, bounded reads, guarded writes."""

import os
from pathlib import Path
import signal
import socket
import stat
import subprocess
import sys
import threading
import time

import pytest

from mag_calibrator_ros.calibration.store import safe_file
from mag_calibrator_ros.calibration.store.safe_file import (
    DEAD_WRITER_GRACE_SECONDS,
    STALE_TEMPORARY_SECONDS,
    FileAccessError,
    read_regular_file,
    remove_stale_temporaries,
    resolve_path,
    write_atomically,
)

LIMIT = 1000


@pytest.fixture
def unix_socket(tmp_path):
    server = socket.socket(socket.AF_UNIX)
    path = tmp_path / 'sock'
    server.bind(str(path))
    yield path
    server.close()


# -- path resolution ------------------------------------------------------------------------------


def test_home_is_expanded_and_paths_made_absolute(monkeypatch, tmp_path):
    monkeypatch.setenv('HOME', str(tmp_path))
    assert resolve_path('~/a/b.yaml') == tmp_path / 'a' / 'b.yaml'
    monkeypatch.chdir(tmp_path)
    assert resolve_path('c.yaml') == tmp_path / 'c.yaml'


@pytest.mark.parametrize(('name', 'message'), [('', 'empty'), ('  ', 'empty'),
                                               ('a\0b', 'NUL'), ('~no_such_user_x/c', 'expand')])
def test_unusable_names_are_refused(name, message):
    with pytest.raises(FileAccessError, match=message):
        resolve_path(name)


def test_a_write_lands_where_a_read_then_looks(tmp_path):
    """'..' past a missing directory: realpath used to send the write elsewhere than the read."""
    name = str(tmp_path / 'missing' / '..' / 'c.yaml')
    write_atomically(resolve_path(name), b'x: 1\n')
    assert read_regular_file(resolve_path(name), LIMIT) == b'x: 1\n'
    assert sorted(os.listdir(tmp_path)) == ['c.yaml']


def test_dot_dot_after_a_symlink_is_what_the_kernel_does(tmp_path):
    (tmp_path / 'real' / 'sub').mkdir(parents=True)
    (tmp_path / 'link').symlink_to(tmp_path / 'real' / 'sub')
    name = str(tmp_path / 'link' / '..' / 'c.yaml')
    write_atomically(resolve_path(name), b'x: 2\n')
    with open(name, 'rb') as kernel_view:  # the OS resolves link/.. as real/
        assert kernel_view.read() == b'x: 2\n'
    assert (tmp_path / 'real' / 'c.yaml').is_file()


# -- reading --------------------------------------------------------------------------------------


def test_missing_directory_and_long_names(tmp_path):
    with pytest.raises(FileAccessError, match='no such file'):
        read_regular_file(tmp_path / 'nowhere', LIMIT)
    with pytest.raises(FileAccessError, match='is a directory'):
        read_regular_file(tmp_path, LIMIT)
    with pytest.raises(FileAccessError, match='File name too long'):
        read_regular_file(tmp_path / ('x' * 300) / 'c.yaml', LIMIT)
    (tmp_path / 'file').write_text('x')
    with pytest.raises(FileAccessError, match='Not a directory'):
        read_regular_file(tmp_path / 'file' / 'c.yaml', LIMIT)


def test_permission_denied_is_named(tmp_path, monkeypatch):
    path = tmp_path / 'c.yaml'
    path.write_text('x')

    def deny(*args, **kwargs):
        raise PermissionError(13, 'Permission denied')

    monkeypatch.setattr(os, 'open', deny)  # root reads anything: simulate what a user sees
    with pytest.raises(FileAccessError, match=f'{path}: cannot read: Permission denied'):
        read_regular_file(path, LIMIT)


def test_devices_and_sockets_are_never_read(unix_socket):
    with pytest.raises(FileAccessError, match='/dev/zero: is a character device'):
        read_regular_file(Path('/dev/zero'), LIMIT)
    with pytest.raises(FileAccessError, match='is a socket'):
        read_regular_file(unix_socket, LIMIT)


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / 'fifo'
    os.mkfifo(fifo)
    outcome = []
    reader = threading.Thread(target=lambda: outcome.append(_attempt(fifo)), daemon=True)
    reader.start()
    reader.join(60.0)
    if reader.is_alive():  # blocked in open(): free it before failing
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(5.0)
        pytest.fail('reading a FIFO blocked until a writer appeared')
    assert 'is a FIFO' in outcome[0]


def _attempt(path):
    try:
        read_regular_file(path, LIMIT)
    except FileAccessError as error:
        return str(error)
    return 'read'


def test_size_is_checked_before_reading(tmp_path, monkeypatch):
    huge = tmp_path / 'huge.yaml'
    with open(huge, 'wb') as file:
        file.truncate(100_000_000)  # sparse: 100 MB without writing them
    monkeypatch.setattr(os, 'read', lambda *args: pytest.fail('read a file over the limit'))
    with pytest.raises(FileAccessError, match='too large .100000000 bytes; the limit is 1000'):
        read_regular_file(huge, LIMIT)


def test_a_file_swapped_or_grown_after_the_check_is_still_bounded(tmp_path, monkeypatch):
    path = tmp_path / 'c.yaml'
    path.write_bytes(b'x' * 100_000)
    small = os.stat_result((stat.S_IFREG | 0o644, 0, 0, 1, 0, 0, 10, 0, 0, 0))
    monkeypatch.setattr(os, 'stat', lambda *args, **kwargs: small)
    monkeypatch.setattr(os, 'fstat', lambda *args, **kwargs: small)
    real_read = os.read
    read = []
    monkeypatch.setattr(os, 'read', lambda fd, n: read.append(n) or real_read(fd, n))
    with pytest.raises(FileAccessError, match='too large'):
        read_regular_file(path, LIMIT)
    assert sum(read) <= LIMIT + 1


def test_the_open_file_is_checked_again(tmp_path, monkeypatch):
    """A FIFO put in place between the check and the open is refused on the descriptor."""
    fifo = tmp_path / 'fifo'
    os.mkfifo(fifo)
    regular = os.stat_result((stat.S_IFREG | 0o644, 0, 0, 1, 0, 0, 10, 0, 0, 0))
    monkeypatch.setattr(os, 'stat', lambda *args, **kwargs: regular)
    with pytest.raises(FileAccessError, match='is a FIFO'):  # opened O_NONBLOCK: no wait
        read_regular_file(fifo, LIMIT)


# -- writing --------------------------------------------------------------------------------------


def test_only_regular_files_or_new_paths_are_written(tmp_path, unix_socket, never_written):
    fifo = tmp_path / 'fifo'
    os.mkfifo(fifo)
    link = tmp_path / 'link'
    link.symlink_to(fifo)
    for target, kind in [(fifo, 'a FIFO'), (link, 'a FIFO'), (unix_socket, 'a socket'),
                         (tmp_path, 'a directory'), (Path('/dev/full'), 'a character device'),
                         (Path('/dev/null'), 'a character device')]:
        with pytest.raises(FileAccessError, match=f'is {kind}.*; only a regular file or a new'):
            write_atomically(resolve_path(target), b'x')
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and stat.S_ISCHR(os.stat('/dev/full').st_mode)
    assert stat.S_ISSOCK(os.stat(unix_socket).st_mode)


def test_a_device_appearing_during_the_write_is_not_replaced(tmp_path, monkeypatch):
    target = tmp_path / 'c.yaml'
    real_fsync = os.fsync

    def fsync_then_fifo(descriptor):
        real_fsync(descriptor)
        if not target.exists():
            os.mkfifo(target)

    monkeypatch.setattr(os, 'fsync', fsync_then_fifo)
    with pytest.raises(FileAccessError, match='is a FIFO'):
        write_atomically(target, b'x')
    assert stat.S_ISFIFO(os.lstat(target).st_mode)
    assert sorted(os.listdir(tmp_path)) == ['c.yaml']  # the temporary is gone


def test_write_keeps_permissions_and_creates_directories(tmp_path):
    target = tmp_path / 'a' / 'b' / 'c.yaml'
    write_atomically(target, b'1')
    assert stat.S_IMODE(target.stat().st_mode) == 0o644
    os.chmod(target, 0o600)
    write_atomically(target, b'2')
    assert target.read_bytes() == b'2' and stat.S_IMODE(target.stat().st_mode) == 0o600


# -- temporaries of interrupted writes ------------------------------------------------------------

INTERRUPTED_WRITER = """
import os, sys, time
from pathlib import Path
from mag_calibrator_ros.calibration.store import safe_file
def hang(*args):
    Path(sys.argv[2]).touch()
    time.sleep(600)
os.replace = hang
safe_file.write_atomically(Path(sys.argv[1]), b'x' * 100)
"""


def test_a_killed_writer_leaves_a_temporary_the_next_write_removes(tmp_path):
    target = tmp_path / 'calibration.yaml'
    write_atomically(target, b'before')
    flag = tmp_path / 'renaming'
    writer = subprocess.Popen([sys.executable, '-c', INTERRUPTED_WRITER, str(target), str(flag)])
    try:
        for _ in range(6000):
            if flag.exists() or writer.poll() is not None:
                break
            time.sleep(0.01)
        assert flag.exists(), 'the writer never reached its rename'
    finally:
        writer.send_signal(signal.SIGKILL)
        writer.wait()
    flag.unlink()
    left = [name for name in os.listdir(tmp_path) if name.endswith('.tmp')]
    assert len(left) == 1 and left[0].startswith(f'.calibration.yaml.{writer.pid}.')
    assert target.read_bytes() == b'before'
    past = time.time() - DEAD_WRITER_GRACE_SECONDS - 1  # the writer died a while ago
    os.utime(tmp_path / left[0], (past, past))
    write_atomically(target, b'after')
    assert sorted(os.listdir(tmp_path)) == ['calibration.yaml']
    assert target.read_bytes() == b'after'


def _temporary(directory, name, age, now):
    path = directory / name
    path.write_text('partial')
    os.utime(path, (now - age, now - age))
    return path


def test_only_our_own_stale_temporaries_of_that_file_are_removed(tmp_path):
    now = time.time()
    target = tmp_path / 'calibration.yaml'
    dead = _finished_pid()
    me = os.getpid()
    old = STALE_TEMPORARY_SECONDS + 1
    removed = [
        _temporary(tmp_path, f'.calibration.yaml.{dead}.abcd_123.tmp', 10, now),  # dead writer
        _temporary(tmp_path, f'.calibration.yaml.{me}.abcdefgh.tmp', old, now),  # abandoned
        _temporary(tmp_path, '.calibration.yaml.k2j4h5g6.tmp', old, now),  # older version
    ]
    kept = [
        _temporary(tmp_path, f'.calibration.yaml.{me}.zzzzzzzz.tmp', 10, now),  # being written
        _temporary(tmp_path, f'.calibration.yaml.{dead}.yyyyyyyy.tmp', 1, now),  # just now
        _temporary(tmp_path, '.calibration.yaml.xxxxxxxx.tmp', 10, now),  # no PID, recent
        _temporary(tmp_path, f'.other.yaml.{dead}.abcdefgh.tmp', old, now),  # another file
        _temporary(tmp_path, f'.calibration.yaml.{dead}.abcdefgh.tmp.bak', old, now),
        _temporary(tmp_path, 'calibration.yaml.abcdefgh.tmp', old, now),  # not hidden
        _temporary(tmp_path, '.calibration.yaml.ABCDEFGH.tmp', old, now),  # not mkstemp's
    ]
    link = tmp_path / f'.calibration.yaml.{dead}.llllllll.tmp'
    link.symlink_to(kept[0])
    directory = tmp_path / f'.calibration.yaml.{dead}.dddddddd.tmp'
    directory.mkdir()
    assert remove_stale_temporaries(target, now=now) == len(removed)
    assert not any(path.exists() for path in removed)
    assert all(path.exists() for path in [*kept, directory]) and link.is_symlink()


@pytest.mark.skipif(os.geteuid() != 0, reason='needs root to give a file away')
def test_another_users_temporaries_are_left_alone(tmp_path):
    now = time.time()
    theirs = _temporary(tmp_path, '.calibration.yaml.abcdefgh.tmp', STALE_TEMPORARY_SECONDS + 1,
                        now)
    os.chown(theirs, 65534, 65534)
    assert remove_stale_temporaries(tmp_path / 'calibration.yaml', now=now) == 0
    assert theirs.exists()


def _finished_pid() -> int:
    process = subprocess.Popen([sys.executable, '-c', 'pass'])
    process.wait()
    return process.pid


def test_reason_and_kinds_for_messages():
    assert safe_file.reason(OSError(28, 'No space left on device')) == 'No space left on device'
    assert safe_file.file_kind(os.stat('/dev/null').st_mode) == 'a character device'
