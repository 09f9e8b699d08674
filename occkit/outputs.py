"""Guarding an output folder: one writer at a time, ``--overwrite`` that deletes only occkit's files, reports beside
an output that never replace anything else, and writes that leave no temporary file behind.

* :class:`OutputLock`: an exclusive lock per output folder, held for the whole run. A second occkit process that
  wants the same folder is refused with one line naming the holder (PID, command, start time). The lock is a
  ``flock`` on ``.<name>.lock`` beside the folder: beside, not inside, because ``occkit sim`` and ``occkit label``
  write a staging folder beside ``--out`` and rename it into place; the kernel drops the lock when its process
  dies, so a crashed run never leaves a stale one.
* :func:`publish_folder` writes a manifest of every file of a finished staging folder (:data:`MANIFEST`) and moves
  it into place; :func:`check_replaceable` lets ``--overwrite`` replace a folder only when every file in it (nested
  ones too) is listed in its manifest or lies in occkit's own cache (:data:`CACHE_FOLDER`).
* :func:`report_beside`, :func:`check_report_file` and :func:`write_report`: the JSON report that describes an
  output file (``model.onnx`` -> ``model.json``) is never the output itself, and replaces only an earlier report of
  the same command.
* :func:`write_atomic`: a file written through a temporary name; a failed write (a full disk among others) removes
  the temporary file and ends as one line naming the file.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import socket
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

from occkit.errors import InputError, UsageError

try:  # Linux and macOS; elsewhere the lock falls back to an exclusive create (see OutputLock)
    import fcntl as _fcntl
except ImportError:  # pragma: no cover - Windows
    _fcntl = None  # type: ignore[assignment]

__all__ = [
    "MANIFEST",
    "CACHE_FOLDER",
    "OutputBusyError",
    "OutputLock",
    "lock_path",
    "staging_folder",
    "manifest_files",
    "file_digest",
    "folder_digest",
    "check_replaceable",
    "check_output_folder",
    "write_manifest",
    "publish_folder",
    "report_beside",
    "check_report_file",
    "write_report",
    "check_not_inside",
    "write_atomic",
    "fsync_folder",
    "write_error",
]

#: The list of every file occkit wrote in a folder, written last, just before the folder is moved into place.
MANIFEST = ".occkit-manifest.json"
MANIFEST_FORMAT = "occkit-manifest/1"
#: The folder occkit's readers add inside a dataset (the index cache): it counts as occkit's.
CACHE_FOLDER = ".occkit"
#: The key :func:`write_report` adds to a report, naming the command that wrote it.
REPORT_KEY = "written_by"


class OutputBusyError(InputError):
    """Another occkit process is writing the output folder."""


# ----------------------------------------------------------------------------------------------------- the lock
def _absolute(path: Path) -> Path:
    """``path`` made absolute with ``..`` resolved textually (the folder need not exist yet)."""
    return Path(os.path.abspath(path))


def lock_path(out: str | Path) -> Path:
    """The lock file of the output folder ``out``: ``.<name>.lock`` in its parent (the real path of the parent, so
    that two spellings of one folder share one lock)."""
    out = _absolute(Path(out))
    if not out.name:  # the file system's root: nothing is beside it
        return out / ".occkit.lock"
    return Path(os.path.realpath(out.parent)) / f".{out.name}.lock"


def staging_folder(out: str | Path) -> Path:
    """The hidden folder beside ``out`` that a run fills before renaming it into place."""
    out = Path(out)
    return out.parent / f".{out.name}.partial"


def _started(seconds: float) -> str:
    """A start time as a user reads it: the clock time, with the date when it was not today."""
    then = time.localtime(seconds)
    if time.strftime("%Y-%m-%d", then) == time.strftime("%Y-%m-%d"):
        return time.strftime("%H:%M:%S", then)
    return time.strftime("%Y-%m-%d %H:%M:%S", then)


def _holder_text(holder: dict[str, Any]) -> str:
    """``PID 1234, occkit sim, started 01:23:45`` from what a lock file holds (what is missing is left out)."""
    parts = [f"PID {holder['pid']}" if isinstance(holder.get("pid"), int) else "PID unknown"]
    if isinstance(holder.get("command"), str):
        parts.append(holder["command"])
    if isinstance(holder.get("started"), (int, float)):
        parts.append(f"started {_started(holder['started'])}")
    if isinstance(holder.get("host"), str) and holder["host"] != socket.gethostname():
        parts.append(f"on {holder['host']}")
    return ", ".join(parts)


def _parse_holder(data: bytes) -> dict[str, Any]:
    try:
        holder = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return holder if isinstance(holder, dict) else {}


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (for the lock of a platform without ``flock``)."""
    if pid <= 0:
        return False
    if sys.platform == "win32":  # pragma: no cover - os.kill(pid, 0) would terminate the process there
        import ctypes

        kernel32 = ctypes.windll.kernel32  # type: ignore[attr-defined]
        handle = kernel32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
        if not handle:
            return kernel32.GetLastError() == 5  # access denied: it exists
        code = ctypes.c_ulong()
        kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
        kernel32.CloseHandle(handle)
        return code.value == 259  # STILL_ACTIVE
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


#: Lock files this process holds, and how many times (a command locks its folder first thing, then the library
#: function it calls locks it again, nested).
_HELD: dict[str, int] = {}
_HELD_GUARD = threading.Lock()
#: The descriptors of the locks this process holds.
_LOCK_FDS: set[int] = set()


def _forget_locks_in_child() -> None:
    """After a fork: close the inherited lock descriptors. A ``flock`` belongs to the open file, which a forked child
    (a DataLoader worker) shares; were it kept, a run killed with SIGKILL would leave its lock to its orphaned workers
    for the seconds they take to notice, and ``--resume auto`` right after would be refused."""
    global _HELD, _HELD_GUARD
    for fd in _LOCK_FDS:
        with contextlib.suppress(OSError):
            os.close(fd)
    _LOCK_FDS.clear()
    _HELD, _HELD_GUARD = {}, threading.Lock()  # the parent's guard may have been held by another thread


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_locks_in_child)


class OutputLock:
    """An exclusive lock on the output folder ``out`` for the whole of a run; use it as a context manager.

    Taking it when another process holds it raises :class:`OutputBusyError` at once (nothing waits), e.g.
    ``--out data/synth is being written by another occkit process (PID 1234, occkit sim, started 01:23:45); wait
    for it or choose another folder``. Under torchrun only rank 0 writes the folder's own files and takes the lock:
    pass ``enabled=False`` on the other ranks. Within one process the lock nests: the command line takes it before
    any work and the library function it calls takes it again.

    With ``flock`` (Linux, macOS) the lock dies with its process; forked children (DataLoader workers) close their
    copy first thing after the fork (a fork hook), so they never outlive it holding the lock. The lock file is
    removed on release; since another process may have opened it just before, a locker checks after locking that the
    path still names the file it locked, and starts again otherwise. Without ``flock`` the lock file is created
    exclusively and holds the PID; a lock file whose process no longer runs is taken over.
    """

    def __init__(self, out: str | Path, command: str, option: str = "--out", enabled: bool = True) -> None:
        self.out, self.command, self.option, self.enabled = Path(out), command, option, enabled
        self.path = lock_path(out)
        self._fd: int | None = None
        self._nested = False
        self._pid = os.getpid()  # the process that took it: a forked child must not release the parent's lock

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:  # fmt: skip
        self.release()

    @property
    def held(self) -> bool:
        return self._fd is not None or self._nested

    def _holder_record(self) -> bytes:
        record = {"pid": os.getpid(), "command": self.command, "started": time.time(), "host": socket.gethostname(),
                  "folder": str(_absolute(self.out))}  # fmt: skip
        return (json.dumps(record) + "\n").encode()

    def _busy(self, holder: dict[str, Any], hint: str = "") -> OutputBusyError:
        return OutputBusyError(f"{self.option} {self.out} is being written by another occkit process "
                               f"({_holder_text(holder)}); wait for it or choose another folder{hint}")  # fmt: skip

    def acquire(self) -> None:
        """Take the lock, or raise :class:`OutputBusyError` naming the process that holds it."""
        if not self.enabled or self.held:
            return
        with _HELD_GUARD:
            if str(self.path) in _HELD:  # this process holds it already
                _HELD[str(self.path)] += 1
                self._nested = True
                return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if _fcntl is None:
                self._acquire_exclusive_create()
            else:
                self._acquire_flock()
        except OSError as error:
            if error.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
                raise
            raise PermissionError(f"cannot write to {self.option} {self.out}: its lock file {self.path} cannot be "
                                  f"created ({error.strerror}); choose a folder whose parent you can write"
                                  ) from error  # fmt: skip
        with _HELD_GUARD:
            _HELD[str(self.path)] = 1
        self._pid = os.getpid()

    def _acquire_flock(self) -> None:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                _fcntl.flock(fd, _fcntl.LOCK_EX | _fcntl.LOCK_NB)
            except OSError as error:
                if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                holder = self._read_holder(fd)
                os.close(fd)
                raise self._busy(holder) from None
            # The holder we waited on may have removed the file between our open and our lock: then the lock is on
            # a file nobody else will find, and the path (if any) is another file; start again.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, self._holder_record())
        self._fd = fd
        _LOCK_FDS.add(fd)

    @staticmethod
    def _read_holder(fd: int) -> dict[str, Any]:
        """What the holder wrote in the lock file; it writes just after locking, so an empty file is read again."""
        for _ in range(20):
            data = os.pread(fd, 4096, 0) if hasattr(os, "pread") else b""
            if data.strip():
                return _parse_holder(data)
            time.sleep(0.01)
        return {}

    def _acquire_exclusive_create(self) -> None:
        for _ in range(2):  # a second try after removing the lock of a process that no longer runs
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                try:
                    holder = _parse_holder(self.path.read_bytes())
                except FileNotFoundError:  # released meanwhile
                    continue
                pid = holder.get("pid")
                if isinstance(pid, int) and not _pid_alive(pid):
                    self.path.unlink(missing_ok=True)
                    continue
                raise self._busy(holder, f" (if no such process runs, delete {self.path})") from None
            os.write(fd, self._holder_record())
            self._fd = fd
            return
        raise self._busy({}, f" (if no occkit process runs, delete {self.path})")

    def release(self) -> None:
        """Remove the lock file and drop the lock (removed first, while still held, so no one takes a dying lock)."""
        if os.getpid() != self._pid:  # a forked child: its copy was closed at the fork, the lock is the parent's
            self._fd, self._nested = None, False
            return
        if self._nested:
            self._nested = False
            with _HELD_GUARD:
                if str(self.path) in _HELD:
                    _HELD[str(self.path)] -= 1
            return
        if self._fd is None:
            return
        with _HELD_GUARD:
            _HELD.pop(str(self.path), None)
        fd, self._fd = self._fd, None
        _LOCK_FDS.discard(fd)
        with contextlib.suppress(OSError):
            if _fcntl is None or os.path.samestat(os.fstat(fd), os.stat(self.path)):
                self.path.unlink()
        os.close(fd)


# ----------------------------------------------------------------------------------------------------- manifests
def _files_under(folder: Path) -> Iterator[str]:
    """Every file under ``folder`` (links included, not followed) as a relative POSIX path."""
    for directory, folders, files in os.walk(folder):
        relative = Path(directory).relative_to(folder)
        # A link to a folder is listed by walk among the folders and not entered: it is an entry of its own.
        for name in [*files, *(f for f in folders if os.path.islink(os.path.join(directory, f)))]:
            yield (relative / name).as_posix()


def write_manifest(folder: Path, command: str) -> Path:
    """Write :data:`MANIFEST` in ``folder``, listing every file in it (relative paths) as written by ``command``.

    Call it last, once nothing more is written in the folder."""
    files = sorted(name for name in _files_under(folder) if name != MANIFEST)
    path = folder / MANIFEST
    path.write_text(json.dumps({"format": MANIFEST_FORMAT, "command": command, "files": files}, indent=0) + "\n")
    return path


def manifest_files(folder: Path) -> tuple[str, frozenset[str]] | None:
    """The command and the files of ``folder``'s manifest, or None when it has none.

    Raises:
        ValueError: the manifest exists but does not read as one (named).
    """
    path = folder / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
        files, command = manifest["files"], manifest["command"]
        if manifest.get("format") != MANIFEST_FORMAT or not isinstance(command, str):
            raise ValueError
        if not isinstance(files, list) or not all(isinstance(name, str) for name in files):
            raise ValueError
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise FileExistsError(f"--overwrite refused: {path} is not a readable occkit manifest (format "
                              f"{MANIFEST_FORMAT}); nothing was deleted") from None  # fmt: skip
    return command, frozenset(files)


def file_digest(path: Path, digest: Any | None = None) -> Any:
    """``digest`` (a new SHA-256 by default) updated with the bytes of ``path``, read in blocks of 1 MB."""
    digest = hashlib.sha256() if digest is None else digest
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest


def folder_digest(folder: Path) -> str:
    """One SHA-256 over the content of ``folder``: each file's relative path and bytes, in sorted order.

    The files are those its manifest lists when it has one (what occkit wrote: a world written by ``occkit sim``),
    otherwise every file but occkit's index cache (:data:`CACHE_FOLDER`), which readers add and rebuild. Two copies
    of a dataset with the same digest hold the same bytes, wherever they lie.

    Raises:
        FileNotFoundError: a file the manifest lists is missing (named).
    """
    folder = Path(folder)
    listed = manifest_files(folder)
    if listed is not None:
        names = sorted(listed[1])
    else:
        names = sorted(n for n in _files_under(folder) if n != MANIFEST and not n.startswith(f"{CACHE_FOLDER}/"))
    digest = hashlib.sha256()
    for name in names:
        path = folder / name
        if not path.is_file():
            raise FileNotFoundError(f"{path} is listed in {folder / MANIFEST} but missing")
        digest.update(f"{name}\0{path.stat().st_size}\0".encode())
        file_digest(path, digest)
    return f"sha256:{digest.hexdigest()}"


def _show(names: Iterable[str], limit: int = 5) -> str:
    names = list(names)
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def check_replaceable(out: Path, command: str, marker: str | None = None) -> None:
    """Refuse to replace ``out`` (``--overwrite``) unless ``command`` wrote it and it holds nothing else.

    A folder qualifies when its :data:`MANIFEST` names ``command`` and lists every file in it, nested ones too;
    files under :data:`CACHE_FOLDER` are occkit's caches and count as listed. An empty or missing folder always
    qualifies. ``marker`` (a file the command always writes) tells a folder of an older occkit, which wrote no
    manifest, from a stranger's in the message.

    Raises:
        FileExistsError: one line naming the folder and up to five files in the way; nothing was deleted.
    """
    if not out.is_dir() or not any(out.iterdir()):
        return
    found = manifest_files(out)
    if found is None:
        if marker is not None and (out / marker).exists():
            raise FileExistsError(f"--overwrite refused: {out} was written by an older occkit, which kept no list of "
                                  f"the files it wrote ({MANIFEST}), so occkit cannot tell them from yours: delete "
                                  "the folder by hand to replace it, or choose another folder; nothing was "
                                  "deleted")  # fmt: skip
        raise FileExistsError(f"--overwrite refused: {out} is not an output of {command} (it has no {MANIFEST}); "
                              "move it away or choose another folder; nothing was deleted")  # fmt: skip
    writer, listed = found
    if writer != command:
        raise FileExistsError(f"--overwrite refused: {out} was written by {writer}, not {command}; choose another "
                              "folder; nothing was deleted")  # fmt: skip
    ours = listed | {MANIFEST}
    foreign = sorted(name for name in _files_under(out) if name not in ours and not name.startswith(CACHE_FOLDER + "/"))
    if foreign:
        raise FileExistsError(f"--overwrite refused: {out} holds files {command} did not write ({_show(foreign)}); "
                              "move them away or choose another folder; nothing was deleted")  # fmt: skip


def check_output_folder(out: Path, overwrite: bool, command: str, marker: str | None = None) -> None:
    """Refuse an ``--out`` folder ``command`` may not write, before any work: a file, a folder with content without
    ``overwrite``, or with ``overwrite`` anything :func:`check_replaceable` refuses. A missing or empty folder passes.

    Raises:
        FileExistsError: one line naming ``out``; nothing was touched.
    """
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a directory")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"--out {out} exists and is not empty; pass --overwrite to replace it")
        check_replaceable(out, command, marker)


def publish_folder(staging: Path, out: Path, command: str, marker: str | None = None) -> None:
    """Move the finished ``staging`` folder to ``out``, its manifest written first.

    An existing ``out`` is checked again (:func:`check_replaceable`: a file may have been added to it during the
    run) and replaced only once the new folder is complete: it is renamed aside, the new one renamed into place,
    and the old one deleted. The caller holds the folder's :class:`OutputLock`.
    """
    write_manifest(staging, command)
    if not out.exists():
        staging.rename(out)
        return
    check_replaceable(out, command, marker)
    retired = out.parent / f".{out.name}.old"
    if retired.exists():  # left by a run killed between the two renames below
        shutil.rmtree(retired)
    out.rename(retired)
    staging.rename(out)
    shutil.rmtree(retired)


# ----------------------------------------------------------------------------------------------------- reports
def report_beside(output: Path, suffix: str = ".json", option: str = "--out") -> Path:
    """The report file that describes the output file ``output``: its name with ``suffix`` (``model.onnx`` ->
    ``model.json``, or ``weights.safetensors`` -> ``weights.report.json`` with ``suffix=".report.json"``).

    Raises:
        UsageError: the report would be ``output`` itself (``--out model.json``).
    """
    report = output.with_suffix(suffix)
    if _absolute(report) == _absolute(output):
        raise UsageError(f"{option} {output}: the report of the run goes to {report.name} beside it, which would "
                         f"replace the output; give the output another suffix")  # fmt: skip
    return report


def check_report_file(report: Path, command: str, option: str = "--out",
                      earlier_keys: Iterable[str] = ()) -> None:  # fmt: skip
    """Refuse (before any work) to write ``report`` over a file that is not an earlier report of ``command``.

    An earlier report is a JSON object that :func:`write_report` wrote for ``command``, or, from an occkit that did
    not mark its reports, one holding every key of ``earlier_keys`` (when given).

    Raises:
        FileExistsError: one line naming the file and what to do.
    """
    if not report.exists() and not report.is_symlink():
        return
    if report.is_file() and not report.is_symlink():
        try:
            found = json.loads(report.read_text())
        except (OSError, UnicodeDecodeError, ValueError):
            found = None
        earlier = set(earlier_keys)
        if isinstance(found, dict) and (found.get(REPORT_KEY) == command or (earlier and earlier <= found.keys())):
            return
    raise FileExistsError(f"{option}: the report goes to {report}, which exists and is not a report of {command}; "
                          "move it away or choose another output name; nothing was written")  # fmt: skip


def write_report(report: Path, payload: dict[str, Any], command: str) -> Path:
    """Write ``payload`` as the JSON ``report`` of ``command`` (marked with :data:`REPORT_KEY`, so a later run
    knows it may replace it), atomically."""
    return write_atomic(report, json.dumps({REPORT_KEY: command, **payload}, indent=2) + "\n")


def check_not_inside(path: Path, folder: Path, option: str, folder_option: str = "--out") -> None:
    """Refuse a file option ``path`` that is ``folder`` or lies in it (a folder a run replaces as a whole).

    Raises:
        UsageError: naming both options.
    """
    file, root = _absolute(path), _absolute(folder)
    if file == root or root in file.parents:
        raise UsageError(f"{option} {path} is inside {folder_option} {folder}, which the run writes and replaces "
                         f"as a whole; write it elsewhere")  # fmt: skip


# ----------------------------------------------------------------------------------------------------- writing
def write_error(error: OSError, path: Path) -> OSError:
    """The one-line error for a failed write of ``path``: ``no space left on device writing <path>`` for a full
    disk (or quota), ``cannot write <path>: <reason>`` otherwise; ``errno`` is kept."""
    if error.errno == errno.ENOSPC:
        message = f"no space left on device writing {path}"
    elif error.errno is not None and error.errno == getattr(errno, "EDQUOT", None):  # not on every platform
        message = f"disk quota exceeded writing {path}"
    else:
        message = f"cannot write {path}: {error.strerror or error}"
    failure = OSError(message)  # one argument: str() is the message alone
    failure.errno = error.errno
    return failure


def fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (a crash right after it keeps the new file); a no-op where the file
    system cannot open folders (the rename is atomic all the same)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes | str) -> Path:
    """Write ``data`` to ``path`` (its folder created if need be) through a temporary file in the same folder and a
    rename, so the file is never seen half written, and flushed to disk. A failed write removes the temporary file
    and raises :func:`write_error`'s one line."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(temporary, "wb") as handle:
            handle.write(data.encode() if isinstance(data, str) else data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except OSError as error:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise write_error(error, path) from error
    fsync_folder(path.parent)
    return path
