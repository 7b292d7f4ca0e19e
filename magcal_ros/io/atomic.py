"""Crash-safe output: write beside the target, swap it in complete, recover what a killed run left.

A new output (a file, or a rosbag2 directory) is written inside a hidden sibling directory
``.<name>.magcal<pid>.<random>.partial`` (the writing process's id in the name, its host in
a ``<name>.owner`` file inside) and moved over the target only when complete and flushed:

- a file replaces a file with one rename (atomic);
- a directory cannot be renamed over a non-empty one, so the old output is first renamed
  into the partial directory (``<name>.replaced``), then the new one is renamed in, then
  the partial directory (with the old output) is deleted. Signals are held off between the
  two renames; a crash there (SIGKILL, power cut) leaves the old output complete, set aside.

Partial directories whose process is gone are dealt with by the next write to the same
target (:func:`recover`): an old output set aside is renamed back when the target is
missing, then the directory is removed. A partial directory of a process that is still
running (a concurrent run), or of another host, is never touched.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import resource
import shutil
import signal
import socket
import sqlite3
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

from magcal_ros.errors import MagcalError

PARTIAL_SUFFIX = ".partial"
ASIDE_SUFFIX = ".replaced"
"""The previous output, set aside inside the partial directory while the new one moves in."""
OWNER_SUFFIX = ".owner"
"""A file inside the partial directory: ``<host> <pid>`` of the writing process."""
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""Signals that stop a run: held off while an output is swapped in."""


def _partial_pattern(name: str) -> re.Pattern[str]:
    """Names of the partial directories of an output called ``name``."""
    return re.compile(rf"^\.{re.escape(name)}\.magcal(\d+)\.[a-z0-9_]+{re.escape(PARTIAL_SUFFIX)}$")


def public_path(path: str | os.PathLike[str]) -> Path:
    """The output a path inside a partial directory will become (the path itself otherwise)."""
    p = Path(path)
    while _partial_pattern(p.name).match(p.parent.name):
        p = p.parent.parent / p.name
    return p


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (a zombie counts as gone)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return True


def _abandoned(partial: Path, name: str, pid: int) -> bool:
    """True when the process that made ``partial`` is gone (and it was on this host)."""
    try:
        host = (partial / (name + OWNER_SUFFIX)).read_text().split()[0]
    except (OSError, IndexError):
        host = None  # killed before writing its owner file: the pid in the name decides
    if host is not None and host != socket.gethostname():
        return False
    return not _pid_alive(pid)


def _restore_aside(partial: Path, dest: Path) -> bool:
    """Put an old output set aside in ``partial`` back at ``dest`` if ``dest`` is missing."""
    aside = partial / (dest.name + ASIDE_SUFFIX)
    if (aside.exists() or aside.is_symlink()) and not (dest.exists() or dest.is_symlink()):
        os.replace(aside, dest)
        return True
    return False


def recover(target: str | os.PathLike[str]) -> list[str]:
    """Clean up after earlier runs killed while writing ``target``; returns one note per action.

    Partial directories of ``target`` whose process is gone are removed; an old output
    one of them had set aside is first renamed back to ``target`` if ``target`` is missing.
    """
    dest = Path(target)
    parent = dest.parent if str(dest.parent) else Path(".")
    pattern = _partial_pattern(dest.name)
    notes: list[str] = []
    try:
        entries = sorted(parent.iterdir())
    except OSError:
        return notes
    for partial in entries:
        m = pattern.match(partial.name)
        if not m or partial.is_symlink() or not partial.is_dir() or not _abandoned(partial, dest.name, int(m.group(1))):
            continue
        try:
            if _restore_aside(partial, dest):
                notes.append(f"restored {dest}, set aside by an interrupted run")
            shutil.rmtree(partial)
        except OSError:
            continue
        notes.append(f"removed {partial.name}, left by an interrupted run")
    return notes


def _fsync_dir(path: Path) -> None:
    """Make renames inside ``path`` durable (where the file system allows it)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT, SIGTERM and SIGHUP (this thread) until the block is done."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _swap_in(new: Path, dest: Path, aside: Path) -> None:
    """Move the complete ``new`` to ``dest``; an old directory goes to ``aside`` first."""
    with _signals_held():
        if new.is_dir() and dest.is_dir():
            os.replace(dest, aside)
            os.replace(new, dest)
        else:
            os.replace(new, dest)
    _fsync_dir(dest.parent)


def file_size_limit() -> int | None:
    """This process's file size limit in bytes (``ulimit -f``), None when unlimited."""
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


SQLITE_FULL = 13
SQLITE_IOERR_WRITE = 778
SQLITE_IOERR_FSYNC = 1034
SQLITE_IOERR_TRUNCATE = 1546


def _sqlite_code(exc: BaseException) -> int | None:
    """The extended SQLite result code of an apsw or sqlite3 error, else None."""
    code = getattr(exc, "extendedresult", None)  # apsw
    if code is None and isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
    return int(code) if isinstance(code, int) else None


def write_failure(exc: BaseException) -> str | None:
    """The real cause, in words, when ``exc`` (or what caused it) is a failed write; else None.

    Recognises ``OSError`` (file size limit, full disk, quota, read-only file system,
    permissions) and SQLite's write errors, which hide the errno: a SQLite write error with
    a file size limit in force is reported as that limit.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    limit = file_size_limit()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno is not None:
            if e.errno == errno.EFBIG:
                return f"file size limit exceeded (ulimit -f: {limit} bytes)" if limit else "file too large"
            if e.errno in (errno.ENOSPC, errno.EDQUOT):
                return "no space left on device" if e.errno == errno.ENOSPC else "disk quota exceeded"
            if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
                return e.strerror or os.strerror(e.errno)
        code = _sqlite_code(e)
        if code == SQLITE_FULL:
            return "no space left on device"
        if code in (SQLITE_IOERR_WRITE, SQLITE_IOERR_FSYNC, SQLITE_IOERR_TRUNCATE):
            return f"file size limit exceeded (ulimit -f: {limit} bytes)" if limit else "write error (disk I/O error)"
        e = e.__cause__ or e.__context__
    return None


def write_target(target: str | os.PathLike[str]) -> Path:
    """Where writing ``target`` really goes: through a symbolic link to the file it points to
    (the link stays a link, its target is updated), else ``target`` itself."""
    path = Path(target)
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike[str], backup: bool = False, mode: int | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success move it to ``target``.

    A symbolic link is written through (:func:`write_target`). A new file gets the mode of
    the file it replaces (a 0600 calibration stays 0600), or ``mode`` when given, or the
    umask's default.

    On any exception (or signal) the temporary file or directory is removed and ``target``
    is left as it was; an ``OSError`` while writing becomes one :class:`MagcalError` line
    naming ``target`` and the cause. With ``backup`` an existing ``target`` file is first
    copied to ``target.bak``. Works for files and for directories (rosbag2 recordings);
    see the module docstring for what a crash leaves and how the next run recovers.
    """
    dest = write_target(target)
    parent = dest.parent if str(dest.parent) else Path(".")
    if mode is None and dest.is_file():
        mode = stat.S_IMODE(dest.stat().st_mode)
    work: Path | None = None
    try:
        try:
            parent.mkdir(parents=True, exist_ok=True)
            recover(dest)
            work = Path(tempfile.mkdtemp(prefix=f".{dest.name}.magcal{os.getpid()}.", suffix=PARTIAL_SUFFIX, dir=parent))
            (work / (dest.name + OWNER_SUFFIX)).write_text(f"{socket.gethostname()} {os.getpid()}\n")
            tmp = work / dest.name
            yield tmp
            if tmp.is_file() and dest.is_dir() or tmp.is_dir() and dest.is_file():
                want, found = ("a file", "a directory") if tmp.is_file() else ("a directory (a rosbag2)", "a file")
                raise MagcalError(f"cannot write {dest}: it is {found}, and this output is {want}; give another name")
            if tmp.is_file():
                if mode is not None:
                    os.chmod(tmp, mode)
                with open(tmp, "rb") as fh:
                    os.fsync(fh.fileno())
            if backup and dest.is_file():
                bak_tmp = work / (dest.name + ".bak")
                shutil.copy2(dest, bak_tmp)
                os.replace(bak_tmp, dest.with_name(dest.name + ".bak"))
            _swap_in(tmp, dest, work / (dest.name + ASIDE_SUFFIX))
        except OSError as exc:
            cause = write_failure(exc)
            if cause is None:
                raise
            raise MagcalError(f"cannot write {dest}: {cause}") from None
    finally:
        if work is not None:
            with contextlib.suppress(OSError):
                _restore_aside(work, dest)
            shutil.rmtree(work, ignore_errors=True)
