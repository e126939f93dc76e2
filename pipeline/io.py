"""Atomic file and directory writes, output locks: a killed run never loses or half-writes work.

Files and directories are written under a temporary name next to their destination and renamed
into place. They get the permissions a plain `open()`/`mkdir()` would give under the user's umask
(not the 0600/0700 of `tempfile`), so another user or container can read `data/`.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from pipeline.errors import UserError

_RENAME_EXCHANGE = 2  # linux/fs.h: swap two paths atomically (renameat2)
_AT_FDCWD = -100


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two existing paths (Linux renameat2); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    rc = renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EPERM):
        return False  # filesystem or kernel without RENAME_EXCHANGE: fall back
    raise OSError(err, os.strerror(err), str(b))


def _aside(path: Path) -> Path:
    return path.parent / f".old-{path.name}"


def recover_dir(path: str | Path) -> Path:
    """Finish a directory replacement that a kill interrupted (fallback path of `atomic_dir`).

    Where `path` is missing but its moved-aside previous version exists, that version is put
    back: the reader sees the last complete directory, never nothing.
    """
    path = Path(path)
    old = _aside(path)
    if not path.exists() and old.is_dir():
        os.replace(old, path)
    return path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success rename it onto `path`.

    The temporary file lives in the same directory, so the final `os.replace` is atomic. On any
    error (or a kill) the destination is untouched and the temporary file is removed (or, after a
    SIGKILL, left as an obviously temporary `.tmp-*` file that no stage reads).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".tmp-{path.name}.", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # After the writer: some (safetensors' save_file) recreate the file owner-only.
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary directory next to `path`; on success it replaces `path` as a whole.

    An existing `path` is swapped with the new directory in one atomic `renameat2` exchange, so
    at every moment `path` is either the complete old directory or the complete new one. Where
    the filesystem cannot exchange, the old one is first renamed to `.old-<name>`; a kill between
    the two renames leaves it there and `recover_dir` (called here and by readers) puts it back.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover_dir(path)
    tmp_path = Path(tempfile.mkdtemp(prefix=f".tmp-{path.name}.", dir=path.parent))
    os.chmod(tmp_path, 0o777 & ~_umask())
    old = _aside(path)
    try:
        yield tmp_path
        _umask_files(tmp_path)
        if not path.exists():
            os.replace(tmp_path, path)
        elif not _exchange(tmp_path, path):
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp_path, path)
    finally:
        recover_dir(path)  # interrupted between the fallback's renames: the old one goes back
        shutil.rmtree(tmp_path, ignore_errors=True)  # after an exchange: the old directory
        shutil.rmtree(old, ignore_errors=True)


def _umask_files(directory: Path) -> None:
    """Give files written in `directory` by libraries that create them owner-only (safetensors'
    `save_file`: 0600) the permissions `open()` gives under the user's umask."""
    mode = 0o666 & ~_umask()
    for file in directory.rglob("*"):
        if file.is_file() and not file.is_symlink() and file.stat().st_mode & 0o777 == 0o600:
            os.chmod(file, mode)


def write_json(path: str | Path, data: Any) -> None:
    """Write `data` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def copy_dir(src: str | Path, dest: str | Path) -> None:
    """Copy the directory `src` onto `dest`, replacing it atomically as a whole."""
    with atomic_dir(dest) as tmp:
        shutil.copytree(src, tmp, dirs_exist_ok=True)


@contextlib.contextmanager
def output_lock(path: str | Path) -> Iterator[None]:
    """Hold an advisory lock on the output `path` while writing it; a second writer is refused.

    The lock is `flock` on `.<name>.lock` next to `path` (released by the kernel when the holder
    dies, even by SIGKILL), holding the holder's PID for the error message.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock_path = path.parent / f".{path.name}.lock"
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise UserError(
                f"{path} is being written by another process (PID {holder}); wait for it to "
                f"finish or stop it (kill {holder})"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)
