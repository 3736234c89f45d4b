# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Small user files read and written safely: one path resolution, bounded reads, atomic writes.

A file name from a parameter can point anywhere: at a device (``/dev/zero`` never ends,
``/dev/full`` must never be replaced), a FIFO (opening it blocks until a writer appears), a
directory, a huge file. Reads here take regular files only, check before opening (a FIFO is
never opened) and again on the open descriptor (the file may have been swapped), and never read
more than asked. Writes go only to a regular file or a new path, through a temporary file in the
same directory that is flushed, renamed over the target and its directory entry flushed, so a
crash leaves the old file or the new one, never a torn one. Temporaries that interrupted writes
left behind are removed by the next write of the same file. Every failure is a
:class:`FileAccessError` whose message starts with the file name.
"""

from __future__ import annotations

import os
from pathlib import Path
import re
import stat
import tempfile
import time

STALE_TEMPORARY_SECONDS = 60.0
"""A temporary of an interrupted write older than this is removed by the next write."""
DEAD_WRITER_GRACE_SECONDS = 5.0
"""... or older than this once the process that wrote it (its PID is in the name) has gone."""

_TEMPORARY_NAME_CHARS = 200  # of the target's name in a temporary's name (NAME_MAX is 255)
# Directory entries looked at for stale temporaries: a crowded directory must not slow every save.
_MAX_SCANNED_ENTRIES = 2_000


class FileAccessError(ValueError):
    """A file cannot be read or written; the message starts with the file and says why."""


class FileMissingError(FileAccessError):
    """The file to read does not exist (a first start, not a fault)."""


def resolve_path(path: str | os.PathLike[str]) -> Path:
    """The one place a user's file name becomes a file, for reading and writing alike.

    ``~`` expanded, made absolute, symlinks followed and ``..`` applied after them
    (``os.path.realpath``; past a missing directory ``..`` is applied to the name), so a write
    lands exactly where a read then looks, and a symlink's target is replaced, not the link.
    """
    try:
        text = os.fspath(path)
    except TypeError:
        raise FileAccessError(f'{path!r} is not a file name') from None
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if not text.strip():
        raise FileAccessError('the file name is empty')
    if '\0' in text:
        raise FileAccessError(f'{text!r}: a file name cannot contain a NUL character')
    expanded = os.path.expanduser(text)
    if expanded.startswith('~'):
        raise FileAccessError(f'{text}: cannot expand {expanded.split(os.sep)[0]!r}')
    try:
        return Path(os.path.realpath(expanded))
    except (OSError, ValueError) as error:
        raise FileAccessError(f'{text}: cannot resolve the path: {reason(error)}') from None


def shown_name(given: str | os.PathLike[str], resolved: Path) -> str:
    """The file as messages name it: as given, plus where it resolves when that differs."""
    text = os.path.expanduser(os.fsdecode(given))
    return text if text == str(resolved) else f'{text} (-> {resolved})'


def read_regular_file(resolved: Path, max_bytes: int, shown: str | None = None) -> bytes:
    """The content of a regular file of at most ``max_bytes``; never blocks, never reads more."""
    shown = shown or str(resolved)
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, 'O_NOCTTY', 0) | getattr(os, 'O_CLOEXEC', 0)
    try:
        _check_readable(os.stat(resolved), max_bytes, shown)  # before open: FIFOs never opened
        descriptor = os.open(resolved, flags)
    except FileNotFoundError:
        raise FileMissingError(f'{shown}: no such file') from None
    except OSError as error:
        raise FileAccessError(f'{shown}: cannot read: {reason(error)}') from None
    try:
        _check_readable(os.fstat(descriptor), max_bytes, shown)  # it may have been swapped
        chunks = []
        remaining = max_bytes + 1
        while remaining > 0:
            chunk = os.read(descriptor, remaining)
            if not chunk:
                break
            chunks.append(chunk)
            remaining -= len(chunk)
    except OSError as error:
        raise FileAccessError(f'{shown}: cannot read: {reason(error)}') from None
    finally:
        os.close(descriptor)
    data = b''.join(chunks)
    if len(data) > max_bytes:
        raise FileAccessError(_too_large(shown, None, max_bytes))
    return data


def _check_readable(status: os.stat_result, max_bytes: int, shown: str) -> None:
    if not stat.S_ISREG(status.st_mode):
        raise FileAccessError(
            f'{shown}: is {file_kind(status.st_mode)}, not a regular file (only regular files '
            f'are read)'
        )
    if status.st_size > max_bytes:
        raise FileAccessError(_too_large(shown, status.st_size, max_bytes))


def _too_large(shown: str, size: int | None, max_bytes: int) -> str:
    have = f'{size} bytes' if size is not None else f'over {max_bytes} bytes'
    return f'{shown}: too large ({have}; the limit is {max_bytes} bytes)'


def write_atomically(target: Path, data: bytes, shown: str | None = None) -> None:
    """Replace ``target`` (already resolved) by ``data``, or create it with its directories.

    Refuses anything at ``target`` that is not a regular file (device node, FIFO, socket,
    directory) and leaves it as it was. A replaced file keeps its permission bits; a new one gets
    0644.
    """
    shown = shown or str(target)
    temporary = None
    try:
        existing = _writable(target, shown)
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(target)
        mode = stat.S_IMODE(existing.st_mode) if existing is not None else 0o644
        descriptor, temporary = tempfile.mkstemp(
            prefix=_temporary_prefix(target), suffix='.tmp', dir=target.parent
        )
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(descriptor, view):]
            os.fchmod(descriptor, mode)
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        _writable(target, shown)  # something else may have appeared there meanwhile
        os.replace(temporary, target)
        temporary = None
        _fsync_directory(target.parent)
    except OSError as error:
        raise FileAccessError(f'{shown}: cannot write: {reason(error)}') from error
    finally:
        if temporary is not None:
            try:
                os.unlink(temporary)
            except OSError:
                pass


def _writable(target: Path, shown: str) -> os.stat_result | None:
    """The target's status if it is a regular file, None for a new path; refuses anything else."""
    try:
        status = os.stat(target)
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(status.st_mode):
        raise FileAccessError(
            f'{shown}: is {file_kind(status.st_mode)}; only a regular file or a new path is '
            f'written, so it was left as it is'
        )
    return status


def _temporary_prefix(target: Path) -> str:
    """``.<name>.<pid>.``: the PID tells a later write whether the writer is still alive."""
    return f'.{target.name[:_TEMPORARY_NAME_CHARS]}.{os.getpid()}.'


def remove_stale_temporaries(target: str | os.PathLike[str], now: float | None = None) -> int:
    """Remove temporaries that interrupted writes of ``target`` left behind; returns how many.

    Only files named like this module's temporaries of that very target
    (``.<name>.<pid>.<8 random>.tmp``, or ``.<name>.<8 random>.tmp`` from older versions),
    regular files (never a symlink) owned by this user, and only when no write can still be
    using them: older than :data:`STALE_TEMPORARY_SECONDS`, or older than
    :data:`DEAD_WRITER_GRACE_SECONDS` when the PID in the name is not running. Best effort:
    errors are ignored.
    """
    target = Path(target)
    now = time.time() if now is None else now
    name = re.escape(f'.{target.name[:_TEMPORARY_NAME_CHARS]}.')
    pattern = re.compile(name + r'(?:(\d{1,10})\.)?[a-z0-9_]{8}\.tmp')
    removed = 0
    try:
        with os.scandir(target.parent) as entries:
            for scanned, entry in enumerate(entries):
                if scanned >= _MAX_SCANNED_ENTRIES:
                    break
                match = pattern.fullmatch(entry.name)
                if match is not None and _stale(entry, match.group(1), now):
                    try:
                        os.unlink(entry.path)
                        removed += 1
                    except OSError:
                        pass
    except OSError:
        pass
    return removed


def _stale(entry: os.DirEntry[str], writer: str | None, now: float) -> bool:
    try:
        status = entry.stat(follow_symlinks=False)
    except OSError:
        return False
    if not stat.S_ISREG(status.st_mode) or status.st_uid != os.geteuid():
        return False
    age = now - status.st_mtime
    if age > STALE_TEMPORARY_SECONDS:
        return True
    return age > DEAD_WRITER_GRACE_SECONDS and writer is not None and not _running(int(writer))


def _running(pid: int) -> bool:
    if pid <= 0:
        return False
    if pid == os.getpid():
        return True  # another thread of this process may be writing
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (OSError, OverflowError):
        return True  # someone else's process, or unknowable: assume it is still writing
    return True


def _fsync_directory(directory: Path) -> None:
    """Make the rename itself durable; some file systems cannot, which is not an error."""
    try:
        descriptor = os.open(directory, os.O_RDONLY | getattr(os, 'O_DIRECTORY', 0))
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def file_kind(mode: int) -> str:
    """'a directory', 'a character device', 'a FIFO (named pipe)' ... for messages."""
    for test, kind in ((stat.S_ISDIR, 'a directory'), (stat.S_ISCHR, 'a character device'),
                       (stat.S_ISBLK, 'a block device'), (stat.S_ISFIFO, 'a FIFO (named pipe)'),
                       (stat.S_ISSOCK, 'a socket'), (stat.S_ISREG, 'a regular file')):
        if test(mode):
            return kind
    return 'not a regular file'


def reason(error: BaseException) -> str:
    """The OS's words for an error ('No space left on device'), without a trailing period."""
    return (getattr(error, 'strerror', None) or str(error)).rstrip('.')
