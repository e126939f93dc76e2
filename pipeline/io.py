"""Atomic file and directory writes, output locks: a killed run never loses or half-writes work.

Files and directories are written under a temporary name next to their destination and renamed
into place. They get the permissions a plain `open()`/`mkdir()` would give under the user's umask
(not the 0600/0700 of `tempfile`), so another user or container can read `data/`.

A stage's outputs go out together (`staged_outputs`): their paths are checked before the work
starts (a file where a folder must be, no permission, a read-only disk: one line naming the path),
each is written under its temporary name, and only when all are written are they renamed into
place, so a failed run leaves the previous outputs as they were and no half of a new set.

Every writer holds an `flock` on its temporary while it writes; a temporary that no live process
holds was left by a killed run, and the next successful write of the same output removes it
(`clean_stale_temps`: only `.tmp-<that output's name>.<random>` names beside it).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
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


_RANDOM = r"[a-z0-9_]{8}"  # what `tempfile` appends to a prefix


def _temp_name(name: str) -> re.Pattern[str]:
    """Names of the temporaries of an output called `name`: `.tmp-<name>.<random>`, and the
    temporary of a temporary (`.tmp-.tmp-<name>.<random>.<random>`: a writer that itself writes
    atomically, given a staged path)."""
    n = re.escape(name)
    return re.compile(rf"\.tmp-(?:{n}\.{_RANDOM}|\.tmp-{n}\.{_RANDOM}\.{_RANDOM})")


def _hold(path: Path) -> tuple[int, bool]:
    """An open descriptor of `path` and whether it holds an flock on it (the mark of a live
    writer): False where another process holds it, or the filesystem cannot lock."""
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return fd, False
    return fd, True


def _new_temp(path: Path, folder: bool) -> tuple[Path, int]:
    """A new temporary file (or folder) next to `path`, and the descriptor holding its lock."""
    if folder:
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{path.name}.", dir=path.parent))
        os.chmod(tmp, 0o777 & ~_umask())
    else:
        fd, name = tempfile.mkstemp(prefix=f".tmp-{path.name}.", dir=path.parent)
        os.close(fd)
        tmp = Path(name)
    return tmp, _hold(tmp)[0]  # unlocked where the filesystem cannot lock: never cleaned then


def clean_stale_temps(path: str | Path) -> list[Path]:
    """Remove the temporaries of the output `path` that killed writers left beside it; return
    them.

    Only the names that `atomic_path`, `atomic_dir` and `staged_outputs` give this output's
    temporaries (`.tmp-<name>.<random>`) are considered, and of those only the ones no live
    process holds (each writer holds an flock on its temporary until it is renamed or removed).
    """
    path = Path(path)
    pattern = _temp_name(path.name)
    removed = []
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        if not pattern.fullmatch(entry.name) or entry.is_symlink():
            continue
        try:
            fd, held = _hold(entry)
        except OSError:  # gone already
            continue
        try:
            if not held:  # a live writer's (or the filesystem cannot tell)
                continue
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed.append(entry)
        finally:
            os.close(fd)
    return removed


def _publish_file(tmp: Path, path: Path) -> None:
    # After the writer: some (safetensors' save_file) recreate the file owner-only.
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, path)


def _publish_dir(tmp: Path, path: Path) -> None:
    """Put the directory `tmp` in place of `path` (swapped in one atomic exchange where the
    filesystem can, else via `.old-<name>`; see `atomic_dir`); the old one is removed."""
    old = _aside(path)
    try:
        _umask_files(tmp)
        if not path.exists():
            os.replace(tmp, path)
        elif not _exchange(tmp, path):
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp, path)
    finally:
        recover_dir(path)  # interrupted between the fallback's renames: the old one goes back
        shutil.rmtree(tmp, ignore_errors=True)  # after an exchange: the old directory
        shutil.rmtree(old, ignore_errors=True)


def _discard(tmp: Path) -> None:
    if tmp.is_dir() and not tmp.is_symlink():
        shutil.rmtree(tmp, ignore_errors=True)
    elif tmp.exists() or tmp.is_symlink():
        tmp.unlink()


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success rename it onto `path`.

    The temporary file lives in the same directory, so the final `os.replace` is atomic. On any
    error (or a kill) the destination is untouched and the temporary file is removed (or, after a
    SIGKILL, left as an obviously temporary `.tmp-*` file that no stage reads, and that the next
    successful write of `path` removes).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp_path, lock = _new_temp(path, folder=False)
    try:
        yield tmp_path
        _publish_file(tmp_path, path)
        clean_stale_temps(path)
    finally:
        try:
            _discard(tmp_path)
        finally:
            os.close(lock)


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
    tmp_path, lock = _new_temp(path, folder=True)
    try:
        yield tmp_path
        _publish_dir(tmp_path, path)
        clean_stale_temps(path)
    finally:
        try:
            recover_dir(path)
            _discard(tmp_path)
            shutil.rmtree(_aside(path), ignore_errors=True)
        finally:
            os.close(lock)


def output_problem(path: str | Path, folder: bool = False) -> str | None:
    """What stops a run from writing the output `path` (a file, or a folder if `folder`), in
    words; None when nothing does that can be seen before trying (a full disk cannot)."""
    path = Path(path)
    if path.exists():
        if folder and not path.is_dir():
            return f"{path} is a file, and a folder is needed there"
        if not folder and path.is_dir():
            return f"{path} is a folder, and a file is needed there"
        where = path.parent
    else:
        where = path.parent
        while not where.exists() and where != where.parent:
            where = where.parent
        if where.exists() and not where.is_dir():
            return f"{where} is a file, and a folder is needed there"
    if not os.access(where, os.W_OK | os.X_OK):
        if _read_only(where):
            return f"{where} is on a read-only file system"
        return f"no permission to write in {where}"
    return None


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def _next_step(problem: str, hint: str) -> str:
    """What to do about an `output_problem`."""
    if "is a file, and a folder" in problem:
        return f"move or delete that file, or {hint}"
    if "is a folder, and a file" in problem:
        return f"move that folder away, or {hint}"
    if problem.startswith("no permission"):
        return f"make it writable for you, or {hint}"
    return hint


def check_outputs(
    files: Iterable[str | Path] = (),
    folders: Iterable[str | Path] = (),
    hint: Callable[[Path], str] | str = "write them elsewhere",
) -> None:
    """Refuse to start a run whose outputs cannot be written (before minutes of work).

    Args:
        files, folders: The outputs, files and folders.
        hint: The way out the message ends with (e.g. "use `--data` elsewhere"), or a function
            of the output path giving it.

    Raises:
        UserError: one line: the output, what is in the way (a file where a folder is needed,
            a folder where a file goes, no permission, a read-only disk) and what to do.
    """
    for path, folder in [*((Path(f), False) for f in files), *((Path(d), True) for d in folders)]:
        problem = output_problem(path, folder)
        if problem is not None:
            raise _cannot_write(path, problem, hint)


def _cannot_write(path: Path, problem: str, hint: Callable[[Path], str] | str) -> UserError:
    way_out = hint(path) if callable(hint) else hint
    return UserError(f"cannot write {path}: {problem}; {_next_step(problem, way_out)}")


class Staging:
    """Temporary paths for a run's outputs (see `staged_outputs`)."""

    def __init__(self, hint: Callable[[Path], str] | str) -> None:
        self._hint = hint
        self._staged: dict[Path, tuple[Path, int, bool]] = {}  # destination -> tmp, lock, folder
        self._made: list[Path] = []  # parent folders this run created

    def file(self, path: str | Path) -> Path:
        """The temporary file to write the output file `path` to (the same one for the same
        `path`); it goes into place when the run's outputs are published."""
        return self._stage(Path(path), folder=False)

    def folder(self, path: str | Path) -> Path:
        """The temporary (empty) folder to fill for the output folder `path`; it replaces
        `path` as a whole when the outputs are published."""
        return self._stage(Path(path), folder=True)

    def write_json(self, path: str | Path, data: Any) -> None:
        """Stage `data` as indented JSON for the output file `path`."""
        self.file(path).write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")

    def _stage(self, path: Path, folder: bool) -> Path:
        if path in self._staged:
            return self._staged[path][0]
        check_outputs(*(((), [path]) if folder else ([path], ())), hint=self._hint)
        try:
            self._make_parents(path.parent)
            if folder:
                recover_dir(path)
            tmp, lock = _new_temp(path, folder)
        except OSError as exc:
            problem = output_problem(path, folder) or exc.strerror or str(exc)
            raise _cannot_write(path, problem, self._hint) from exc
        self._staged[path] = (tmp, lock, folder)
        return tmp

    def _make_parents(self, folder: Path) -> None:
        missing = []
        while not folder.exists() and folder != folder.parent:
            missing.append(folder)
            folder = folder.parent
        for made in reversed(missing):
            made.mkdir(exist_ok=True)
            self._made.append(made)

    def publish(self) -> None:
        """Move every staged output into place, in the order they were staged."""
        for path, (tmp, _, folder) in self._staged.items():
            if folder:
                _publish_dir(tmp, path)
            else:
                _publish_file(tmp, path)
            clean_stale_temps(path)
        self._made.clear()  # they hold outputs now

    def discard(self) -> None:
        """Remove what was staged and not published, and the parent folders made for it (where
        they are still empty)."""
        for tmp, lock, _ in self._staged.values():
            try:
                _discard(tmp)
            finally:
                os.close(lock)
        self._staged.clear()
        for made in reversed(self._made):
            with contextlib.suppress(OSError):
                made.rmdir()
        self._made.clear()


@contextlib.contextmanager
def staged_outputs(
    files: Iterable[str | Path] = (),
    folders: Iterable[str | Path] = (),
    hint: Callable[[Path], str] | str = "write them elsewhere",
) -> Iterator[Staging]:
    """A run's outputs, published together or not at all.

    The outputs named here are checked first (`check_outputs`), so a path that cannot be written
    fails before the work. Inside the block each output is written to its temporary
    (`Staging.file`, `Staging.folder`; outputs not named here may be staged too); when the block
    ends without an error, all are renamed into place one after the other (each rename atomic),
    and the stale temporaries of killed runs beside them are removed. On an error nothing is
    published: the previous outputs stay as they were, and the temporaries are removed.
    """
    files, folders = list(files), list(folders)
    check_outputs(files, folders, hint)
    staging = Staging(hint)
    try:
        yield staging
        staging.publish()
    finally:
        staging.discard()


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
