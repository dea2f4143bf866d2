"""Atomic file writing, shared by every verb that writes a file.

A file is written to a temporary file in the destination's own directory,
flushed and fsync'ed, then renamed over the destination with ``os.replace``
(atomic on POSIX and Windows when both names are on one file system). A reader
therefore sees either the old file or the complete new one, never a prefix; a
failure at any point (disk full, permission, Ctrl-C) removes the temporary file
and leaves an existing destination untouched.

User mistakes (output path is a directory or a write-protected file, directory
missing or read-only) raise :class:`UserError`, a ``ValueError`` the CLI prints as one line before
exiting with status 2.
"""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

__all__ = ["UserError", "atomic_write_bytes", "atomic_write_text", "check_writable"]

# Permission bits of a newly created file before the umask is applied, as
# open(2) uses for an ordinary `open(path, "w")`.
NEW_FILE_MODE = 0o666


class UserError(ValueError):
    """A mistake in the user's input or environment, reported as one line.

    The CLI prints ``str(err)`` and exits with status 2; no traceback.
    """


def _current_umask() -> int:
    # os.umask can only be read by setting it; restore it at once.
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _check_destination(path: Path) -> None:
    if path.is_dir():
        raise UserError(f"cannot write {path}: it is a directory; give a file name")
    parent = path.parent
    if not parent.exists():
        raise UserError(f"cannot write {path}: directory {parent} does not exist")
    if not parent.is_dir():
        raise UserError(f"cannot write {path}: {parent} is not a directory")
    if path.exists() and _write_protected(path):
        raise UserError(f"cannot write {path}: the file is read-only; make it writable or choose another name")


def _write_protected(path: Path) -> bool:
    """An existing file nobody may write (no w permission bits), or one this user may not write.

    The permission bits are read, not only access(2): a rename replaces a file with
    the directory's permission alone, and root passes every access check, so an
    atomic write would otherwise replace a write-protected file silently.
    """
    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return (mode & 0o222) == 0 or not os.access(path, os.W_OK)


def check_writable(path) -> Path:
    """Check before any long work that ``path`` can be written; return it as a Path.

    The same checks as :func:`atomic_write_bytes` (a directory, a missing or
    non-directory parent, a write-protected file), then a probe: a temporary file
    is created in the destination's directory and removed at once, so a
    read-only directory or file system is reported before anything is measured,
    fitted or drawn. Nothing is left behind. Raises :class:`UserError`.
    """
    path = Path(os.fspath(path))
    _check_destination(path)
    fd, tmp_name = _make_temp(path)
    os.close(fd)
    try:
        os.unlink(tmp_name)
    except FileNotFoundError:
        pass
    return path


def _make_temp(path: Path) -> tuple[int, str]:
    """mkstemp beside ``path``; a failure is a UserError naming the directory."""
    parent = path.parent
    try:
        return tempfile.mkstemp(dir=parent, prefix=f".{path.name}.", suffix=".tmp")
    except PermissionError as exc:
        raise UserError(f"cannot write {path}: directory {parent} is not writable") from exc
    except OSError as exc:
        reason = "read-only file system" if exc.errno == errno.EROFS else (exc.strerror or str(exc))
        raise UserError(f"cannot write {path}: {reason}") from exc


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; return the path written.

    path : str or os.PathLike, destination file (created or replaced).
    data : bytes-like, the complete new content.

    The new file keeps the permission bits of the file it replaces, or gets
    the usual ``0o666 & ~umask`` when new. Raises :class:`UserError` naming
    the problem when the destination is a directory, its directory is missing
    or not writable, or writing fails (e.g. disk full); the temporary file is
    removed and an existing destination is left intact in every case.
    """
    path = Path(os.fspath(path))
    data = bytes(data)
    _check_destination(path)
    parent = path.parent
    fd, tmp_name = _make_temp(path)
    tmp = Path(tmp_name)
    try:
        try:
            mode = path.stat().st_mode & 0o7777
        except FileNotFoundError:
            mode = NEW_FILE_MODE & ~_current_umask()
        with os.fdopen(fd, "wb") as fh:
            fd = -1  # now owned by fh
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as exc:
        if fd >= 0:
            os.close(fd)
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            reason = "disk full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
            raise UserError(f"cannot write {path}: {reason}; the existing file is unchanged") from exc
        raise
    _fsync_directory(parent)
    return path


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write_bytes`).

    text : str, encoded with ``encoding`` before anything touches the disk, so
        an encoding error leaves the destination untouched too.
    """
    return atomic_write_bytes(path, text.encode(encoding))


def _fsync_directory(directory: Path) -> None:
    """Make the rename durable (best effort: not every OS can open a directory)."""
    try:
        dfd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)
