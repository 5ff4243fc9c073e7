"""Output places: checked before any work, locked while a run writes there, staged, and committed whole.

* :func:`check_place`: the place can hold output, before any work: not on a system file system (``/proc``,
  ``/sys``, ``/dev``), no file where a folder is expected, writable, enough free space.
* :func:`lock_place`: one run at a time per output place (``fcntl.flock`` on a lock file of the user's temporary
  folder, named after the place); a second run fails at once with :class:`OutputBusyError`. :func:`release_places`
  releases every lock this process holds (the command line does it when a command ends; the kernel does it when the
  process dies).
* :func:`staged_folder`: a hidden folder beside the output (``.OUT.<pid>-<random>.staging``) is written into and
  moved into place only when the whole command succeeds; on any failure, an interruption included, it is removed
  with the folders made for it. Staging folders left by a run that was killed (its process is gone) are removed at
  the next run into the same place, with a line saying so. Before anything moves, every file it would replace is
  checked against the record of what reachplan wrote (:mod:`reachplan.imaging.files`): a file reachplan did not
  write is never overwritten.
* :func:`written_file`: the same for one output file written in place (atomically).

Every failure of the place itself (a full disk, a read-only or system file system, a file in the way) is a typed
error (:class:`OutputPlaceError`) that names the place as the user gave it, never a staging path.
"""

from __future__ import annotations

import atexit
import errno
import hashlib
import os
import re
import secrets
import shutil
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path

from reachplan import ReachplanError
from reachplan.imaging.errors import OutputBusyError, OutputPlaceError
from reachplan.imaging.files import (
    MANIFEST,
    atomic_write_bytes,
    file_digest,
    manifest_bytes,
    missing_folders,
    read_manifest,
    record_written,
    refuse_foreign,
    remove_folders,
)

#: file system types that hold no user files (the kernel's views of itself, devices, control groups)
SYSTEM_FILE_SYSTEMS = frozenset({
    "proc", "sysfs", "devtmpfs", "devpts", "cgroup", "cgroup2", "debugfs", "tracefs", "securityfs", "pstore", "bpf",
    "configfs", "fusectl", "mqueue", "binfmt_misc", "autofs", "efivarfs", "hugetlbfs", "rpc_pipefs", "nsfs",
    "selinuxfs",
})
#: the kernel's own trees on Linux, whatever is mounted inside them (/dev is a tmpfs in some containers), and the
#: one place for files among them (POSIX shared memory)
_KERNEL_TREES = (Path("/proc"), Path("/sys"), Path("/dev"))
_USER_TREES = (Path("/dev/shm"),)
#: errors of writing that are about the place whatever file they name
_PLACE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS}
#: errors that are about the place when they name a path inside it (or none)
_PATH_ERRNOS = {errno.EACCES, errno.EPERM, errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENOTEMPTY,
                errno.EXDEV, errno.EINVAL}


def _nearest_existing(path: Path) -> Path:
    while not path.exists() and path.parent != path:
        path = path.parent
    return path


def _unescape(field: str) -> str:
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), field)


def file_system_type(path: Path) -> str | None:
    """Return the type of the file system holding ``path`` (Linux: ``/proc/self/mountinfo``); None when unknown.

    Parameters
    ----------
    path : Path
        An existing path (resolved: the longest mount point above it wins).

    Returns
    -------
    str or None
        E.g. ``"ext4"``, ``"tmpfs"``, ``"proc"``; None off Linux or when the mount table cannot be read.
    """
    try:
        lines = Path("/proc/self/mountinfo").read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None
    best, kind = -1, None
    for line in lines:
        head, sep, tail = line.partition(" - ")
        fields = head.split()
        if not sep or len(fields) < 5 or not tail.split():
            continue
        mount = Path(_unescape(fields[4]))
        if (path == mount or mount in path.parents) and len(mount.parts) > best:
            best, kind = len(mount.parts), tail.split()[0]
    return kind


def _system_place(path: Path) -> str | None:
    """Return the system file system ``path`` lies on (e.g. proc, sysfs), or None for an ordinary one."""
    kind = file_system_type(path)
    if kind in SYSTEM_FILE_SYSTEMS:
        return kind
    if sys.platform.startswith("linux") and not any(path == t or t in path.parents for t in _USER_TREES):
        for tree in _KERNEL_TREES:
            if path == tree or tree in path.parents:
                return kind or tree.name
    return None


def check_place(path: Path, given: Path, option: str, *, folder: bool, need_mb: float) -> None:
    """Check, before any work, that ``path`` can hold a command's output.

    Parameters
    ----------
    path : Path
        The output, resolved: a folder (``folder``) or a file.
    given : Path
        The output as the user gave it (named in the messages).
    option : str
        The option that gave it (e.g. ``"--out"``).
    folder : bool
        ``path`` is a folder (it may exist); otherwise a file (its folder may exist).
    need_mb : float
        Free space the output needs at least, MB.

    Raises
    ------
    OutputPlaceError
        ``path`` lies on a system file system, a file stands where a folder is expected, the place is read-only
        or not writable, or the device has less than ``need_mb`` free.
    """
    probe = _nearest_existing(path if folder else path.parent)
    system = _system_place(probe)
    if system is not None:
        raise OutputPlaceError(f"{option} {given}: {probe} is on a system file system ({system}), which holds no "
                               "user files; choose an output place on a disk")
    # a folder is staged beside itself: its parent is written too
    for place in dict.fromkeys([probe, _nearest_existing(path.parent)]):
        if not place.is_dir():
            raise OutputPlaceError(f"{option} {given}: {place} is a file, not a folder; choose another output place")
        readonly = bool(os.statvfs(place).f_flag & os.ST_RDONLY) if hasattr(os, "statvfs") else False
        if readonly or not os.access(place, os.W_OK | os.X_OK):
            why = "is on a read-only file system" if readonly else "is not writable"
            raise OutputPlaceError(f"{option} {given}: {place} {why}; choose a writable output place")
    free_mb = shutil.disk_usage(probe).free / 1e6
    if free_mb < need_mb:
        raise OutputPlaceError(f"{option} {given}: the device holding {probe} has {free_mb:.1f} MB free; the output "
                               f"needs about {need_mb:.0f} MB: free some space or choose another output place")


# --- one run at a time per place ---------------------------------------------------------------------------------

_held: dict[str, tuple[int, Path]] = {}  # place -> (open lock file, its path): this process's locks


def _lock_folder() -> Path:
    uid = os.getuid() if hasattr(os, "getuid") else os.getlogin()
    folder = Path(tempfile.gettempdir()) / f"reachplan-locks-{uid}"
    folder.mkdir(mode=0o700, exist_ok=True)
    return folder


def lock_place(path: Path, given: Path, option: str) -> None:
    """Take the lock of the output place ``path`` for this process (a second call for the same place does nothing).

    Parameters
    ----------
    path : Path
        The output folder or file, resolved (the lock's name is derived from it).
    given : Path
        The place as the user gave it (for the message).
    option : str
        The option that gave it.

    Raises
    ------
    OutputBusyError
        Another process holds the lock: a run writing to the same place.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        return
    key = str(path)
    if key in _held:
        return
    try:
        lock = _lock_folder() / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.lock"
    except OSError:  # pragma: no cover - no usable temporary folder: run without the lock
        return
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 100).decode(errors="replace").split(" ")[0]
            os.close(fd)
            raise OutputBusyError(f"{option} {given}: another reachplan run (process {holder or '?'}) is writing "
                                  "there; wait for it to finish or choose another output place") from None
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:  # the holder released it (and removed the file) meanwhile
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} {key}\n".encode())
    if not _held:
        atexit.register(release_places)  # a process that ends without releasing still removes its lock files
    _held[key] = (fd, lock)


def release_places() -> None:
    """Release every output-place lock this process holds (and remove their lock files)."""
    while _held:
        _, (fd, lock) = _held.popitem()
        with suppress(OSError):
            lock.unlink()  # before unlocking: a run that opens the old file then sees it is gone and retries
        os.close(fd)


# --- staging -----------------------------------------------------------------------------------------------------


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process, or no signals here
        return True
    return True


def remove_stale_stages(out: Path) -> list[Path]:
    """Remove the staging folders of ``out`` left by runs whose process is gone; print a line for each.

    Run only under ``out``'s lock (:func:`lock_place`): no live reachplan run is then staging for ``out``. A staging
    folder without a process number (an older reachplan's) counts as stale.

    Parameters
    ----------
    out : Path
        The output folder, resolved.

    Returns
    -------
    list of Path
        The folders removed.
    """
    pattern = re.compile(rf"^\.{re.escape(out.name)}\.(?:(\d+)-)?\w+\.staging$")
    removed = []
    with suppress(OSError):
        for entry in out.parent.iterdir():
            match = pattern.match(entry.name)
            if not match or not entry.is_dir() or entry.is_symlink():
                continue
            pid = int(match.group(1)) if match.group(1) else None
            if pid is not None and (pid == os.getpid() or _alive(pid)):
                continue
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
            print(f"reachplan: removed {entry}, a staging folder left by an interrupted run"
                  f"{'' if pid is None else f' (process {pid})'}", file=sys.stderr)
    return removed


def _new_stage(out: Path) -> Path:
    while True:
        stage = out.parent / f".{out.name}.{os.getpid()}-{secrets.token_hex(4)}.staging"
        try:
            stage.mkdir(0o777)  # less the umask: the folder becomes the output as it is
            return stage
        except FileExistsError:  # pragma: no cover - a 32-bit name taken: draw another
            continue


def place_error(exc: BaseException, given: Path, option: str, internal: Sequence[Path]) -> ReachplanError | None:
    """Return the typed error for a failure while writing into a place (None: re-raise ``exc`` as it is).

    An ``OSError`` about the place (no space, read-only, permission, a file in the way) becomes an
    :class:`OutputPlaceError` naming ``given``; a reachplan error whose message names an internal path has that path
    replaced by ``given`` (in place).

    Parameters
    ----------
    exc : BaseException
        What was raised.
    given : Path
        The place as the user gave it.
    option : str
        The option that gave it.
    internal : sequence of Path
        The paths written into (staging folder, output folder): an error naming a path below one of them is the
        place's.

    Returns
    -------
    ReachplanError or None
        The error to raise instead, or None.
    """
    if isinstance(exc, ReachplanError):
        if exc.args and isinstance(exc.args[0], str):
            text = exc.args[0]
            for p in internal:
                text = text.replace(str(p), str(given))
            exc.args = (text, *exc.args[1:])
        return None
    if not isinstance(exc, OSError) or exc.errno is None:
        return None
    named = [Path(os.fsdecode(f)) for f in (exc.filename, exc.filename2) if f is not None]
    inside = not named or any(p == root or root in p.parents for p in named for root in internal)
    if exc.errno not in _PLACE_ERRNOS and not (exc.errno in _PATH_ERRNOS and inside):
        return None
    why = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "the disk quota is exhausted",
           errno.EFBIG: "a file is too large for the file system",
           errno.EROFS: "the file system is read-only"}.get(exc.errno, f"cannot write there ({exc.strerror or exc})")
    todo = "free some space or choose" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "choose"
    return OutputPlaceError(f"{option} {given}: {why}; nothing was written: {todo} another output place")


@contextmanager
def place_errors(place: Path, given: Path | None = None, option: str = "--out") -> Iterator[None]:
    """Turn the failures of writing into ``place`` into typed errors naming it as given (:func:`place_error`).

    Parameters
    ----------
    place : Path
        The output folder or file written in the block, resolved.
    given : Path or None
        ``place`` as the user gave it (default ``place``).
    option : str
        The option that gave it.

    Yields
    ------
    None
        The caller writes in the block.

    Raises
    ------
    OutputPlaceError
        The place failed (no space, read-only, ...).
    """
    try:
        yield
    except BaseException as exc:
        mapped = place_error(exc, place if given is None else Path(given), option, (place,))
        if mapped is None:
            raise
        raise mapped from None


@contextmanager
def staged_folder(out: Path, given: Path | None = None, option: str = "--out") -> Iterator[Path]:
    """Give a hidden folder beside ``out`` to write into, moved into place when the block succeeds.

    On success the staged files move into ``out`` (created when missing; folders merge, files replace their
    namesakes, nothing else in ``out`` is touched) after every file they replace has been checked: a file there
    that reachplan did not write stops the move before anything moves. The files are added to ``out``'s record of
    what reachplan wrote. On any failure (an interruption too) the staging folder and the folders made for it are
    removed and ``out`` is left as it was.

    Parameters
    ----------
    out : Path
        The folder the results end up in.
    given : Path or None
        ``out`` as the user gave it (named in errors; default ``out``).
    option : str
        The option that gave it.

    Yields
    ------
    Path
        The staging folder (same file system as ``out``, so every move is a rename).

    Raises
    ------
    OutputPlaceError
        The place failed (no space, read-only, a file where a folder goes), named as the user gave it.
    OutputExistsError
        A file in ``out`` that reachplan did not write would be replaced.
    """
    out = Path(out).resolve()
    given = out if given is None else Path(given)
    created = missing_folders(out.parent)
    with place_errors(out.parent, given, option):
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_stages(out)
            stage = _new_stage(out)
        except BaseException:
            remove_folders(created)
            raise
    try:
        yield stage
        _commit(stage, out, given, option)
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        remove_folders(created)
        mapped = place_error(exc, given, option, (stage, out))
        if mapped is None:
            raise
        raise mapped from None


def _commit(stage: Path, out: Path, given: Path, option: str) -> None:
    """Check what the staged files would replace in ``out``, record them, then move them in (renames)."""
    entries = {p.relative_to(stage).as_posix(): file_digest(p)
               for p in sorted(stage.rglob("*")) if p.is_file() and p.name != MANIFEST}
    if not out.exists():
        atomic_write_bytes(stage / MANIFEST, manifest_bytes(entries))
        os.replace(stage, out)
        return
    record = read_manifest(out)
    for rel in sorted({*entries, *(p.relative_to(stage).as_posix() for p in stage.rglob(MANIFEST))}):
        target = out / rel
        for folder in reversed(target.relative_to(out).parents[:-1]):
            if (out / folder).exists() and not (out / folder).is_dir():
                raise OutputPlaceError(f"{option} {given}: {given / folder} is a file where reachplan writes a "
                                       "folder; move it away or choose another output place")
        if not (target.is_file() and not target.is_symlink() and rel in record and record[rel] == file_digest(target)):
            refuse_foreign([target], f"{option} {given}")
    atomic_write_bytes(stage / MANIFEST, manifest_bytes({**record, **entries}))
    _merge(stage, out)
    shutil.rmtree(stage, ignore_errors=True)


def _merge(src: Path, dest: Path) -> None:
    for entry in sorted(src.iterdir()):
        target = dest / entry.name
        if entry.is_dir() and not entry.is_symlink() and target.is_dir() and not target.is_symlink():
            _merge(entry, target)
        else:
            os.replace(entry, target)


@contextmanager
def written_file(out: Path, given: Path | None = None, option: str = "--out") -> Iterator[None]:
    """Around the (atomic) writing of one output file: typed errors naming it, and the record of it.

    The file must not exist unless reachplan wrote it (checked on entry). On success it is added to its folder's
    record of what reachplan wrote; on failure the new file (if the failure came after it) and the folders made
    for it are removed.

    Parameters
    ----------
    out : Path
        The file to write, resolved.
    given : Path or None
        ``out`` as the user gave it (default ``out``).
    option : str
        The option that gave it.

    Yields
    ------
    None
        The caller writes ``out`` in the block.

    Raises
    ------
    OutputPlaceError
        The place failed (no space, read-only, ...), named as the user gave it.
    OutputExistsError
        ``out`` exists and reachplan did not write it.
    """
    out = Path(out)
    given = out if given is None else Path(given)
    refuse_foreign([out], f"{option} {given}")
    created = missing_folders(out.parent)
    before = out.stat().st_mtime_ns if out.exists() else None
    with place_errors(out.parent, given, option):
        try:
            yield
            record_written(out.parent, {out: file_digest(out)})
        except BaseException:
            if out.exists() and out.stat().st_mtime_ns != before:  # written, but not recorded: not kept
                out.unlink()
            remove_folders(created)
            raise
