"""Safe writes of output files: atomic, only where the user asked, with the usual permissions.

Rules (see ``docs/guide/reliability.md``):

* A file is written to a temporary name beside it and renamed over the target at the end, so
  a crash, Ctrl-C or SIGTERM never leaves a half-written file; the temporary file is removed.
* The target must be a regular file or not exist yet.  A symbolic link is followed: its
  target is written (as a shell's ``>`` does) and the link stays.  A folder, FIFO, socket or
  device is refused.
* A new file gets the permissions the umask allows (``0644`` under the usual ``022``); an
  existing file keeps its mode.
* Missing parent folders are created (as ``mkdir -p`` does) when the file is written, not
  before: a write that fails removes the folders it created, so a failed run leaves nothing.
* :func:`check_output_path` tells before any work whether a path can be written: its folder
  exists, or can be created in the nearest folder that does, is writable, its name is not too
  long, and it is not one of the run's input files.  The temporary name is short (``.`` + at
  most 32 characters of the name + a random suffix + ``.tmp``), so any name the file system
  takes can be written.

Kept free of any other flyvpr import so every layer can use it.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import re
import secrets
import socket
import stat
import time
import zipfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "OutputPathError",
    "atomic_open",
    "check_output_path",
    "make_folders",
    "raise_interruption",
    "remove_folders",
    "resolve_output",
    "write_bytes_atomic",
    "write_text_atomic",
    "write_json_atomic",
]

logger = logging.getLogger(__name__)

#: characters of the target's name kept in its temporary file's name (to tell whose it is)
_TMP_STEM = 32
_O_BINARY = getattr(os, "O_BINARY", 0)


class OutputPathError(ValueError):
    """An output path that must not or cannot be written (checked before any work)."""


def resolve_output(path) -> Path:
    """The file that writing ``path`` would replace: ``path``, or a symlink's final target.

    Raises
    ------
    OutputPathError
        For a symlink loop, or an existing target that is not a regular file.
    """
    path = Path(path)
    target = path
    if path.is_symlink():
        try:
            target = Path(os.path.realpath(path, strict=False))
            os.stat(path)  # raises ELOOP on a loop; a dangling link is fine (writes its target)
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise OutputPathError(
                f"{path}: cannot write through this link ({exc.strerror})"
            ) from None
    try:
        st = os.stat(target)
    except (FileNotFoundError, NotADirectoryError):
        return target  # nothing to replace; the folder is checked by the caller
    except OSError as exc:
        raise OutputPathError(f"{path}: cannot write it ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        kind = _kind(st.st_mode)
        raise OutputPathError(
            f"{path} is {kind}, not a regular file: refusing to replace it; name a file"
        )
    return target


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "not a regular file"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_output_path(
    path, inputs: Iterable = (), *, what: str = "output", image_extensions: Iterable[str] = ()
) -> Path:
    """Check, before any work, that ``path`` can and may be written; return the file to write.

    Parameters
    ----------
    path : str or Path
        The output the user named.
    inputs : iterable of str or Path
        Every file the run reads (images, model, CSV, ground truth, config): the output must
        be none of them.  Folders among them are skipped.
    what : str
        How the message names the output, e.g. ``"--out"``.
    image_extensions : iterable of str
        Suffixes of image files (``flyvpr.images.IMAGE_EXTENSIONS``): given, the output may not
        go into a folder of images among the inputs, nor below one (a folder an input image
        file lies in, or an input folder holding an image file): a later run on that folder
        would refuse the file, or the sub-folder.

    Returns
    -------
    Path
        The file that will be replaced or created (a symlink's target).

    Raises
    ------
    OutputPathError
        If the output is an input of the run, is not a regular file, its folder (or the
        nearest existing folder above a missing one) is not a folder or not writable, or its
        name is too long for the file system.  Missing folders are not created here.
    """
    path = Path(path)
    inputs = list(inputs)  # (read twice)
    shown = f"{what} {path}"
    # Before resolve_output: a name over the limit makes even stat fail (ENAMETOOLONG).
    _check_name_length(path, shown)
    try:
        target = resolve_output(path)
    except OutputPathError as exc:
        raise OutputPathError(f"{what} {exc}") from None
    # A file that does not exist yet is no input; otherwise compare (device, inode) pairs.
    for item in inputs if os.path.lexists(target) else ():
        item = Path(item)
        if _same_file(target, item):
            raise OutputPathError(
                f"{shown} is an input of this run ({item}): refusing to overwrite it; "
                "choose another output file"
            )
    # Not into a folder of images the run reads, nor below it: the next run on that folder
    # would refuse the file or the sub-folder (an image folder holds images only)
    where = Path(os.path.realpath(target.parent))
    for folder in _image_folders(inputs, tuple(image_extensions)) if image_extensions else ():
        real = Path(os.path.realpath(folder))
        if where == real or real in where.parents:
            raise OutputPathError(
                f"{shown} would go into {folder}, a folder of images this run reads, where every "
                "later run would refuse it (not an image): choose another folder"
            )
    # Missing folders are created when the file is written; here, only check that they can be.
    missing = _missing_folders(target.parent)
    folder = missing[0].parent if missing else target.parent
    if not folder.is_dir():
        raise OutputPathError(f"{shown}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(f"{shown}: folder {folder} is not writable")
    for sub in missing:
        _check_name_length(sub, shown)
    _check_name_length(target, shown)  # a symlink's target has a name of its own
    return target


def _image_folders(inputs: Iterable, extensions: tuple[str, ...]) -> list[Path]:
    """The folders of images among a run's inputs: those of its image files (``extensions``),
    and input folders that hold an image file (a recording's folder; not a ROS 2 bag's)."""
    folders: list[Path] = []
    for item in map(Path, inputs):
        if item.suffix.lower() in extensions:
            if item.parent not in folders:
                folders.append(item.parent)
        elif item.is_dir() and item not in folders:
            try:
                with os.scandir(item) as entries:
                    if any(Path(e.name).suffix.lower() in extensions for e in entries):
                        folders.append(item)
            except OSError:
                continue
    return folders


def _missing_folders(folder: Path) -> list[Path]:
    """The folders of ``folder``'s path that do not exist, outermost first."""
    missing = []
    while not os.path.lexists(folder) and folder.parent != folder:
        missing.append(folder)
        folder = folder.parent
    return missing[::-1]


def make_folders(folder) -> list[Path]:
    """Create ``folder`` and any missing folders above it, as ``mkdir -p`` does.

    For writers that cannot go through :func:`atomic_open` (a file flushed record by record,
    a third-party sink): call it just before the file is opened, and pass its result to
    :func:`remove_folders` if opening fails.

    Returns
    -------
    list of Path
        The folders created, outermost first (one another process made meanwhile is not ours).
    """
    created = []
    for sub in _missing_folders(Path(folder)):
        try:
            os.mkdir(sub)
        except FileExistsError:
            if not sub.is_dir():
                raise
        else:
            created.append(sub)
    return created


def raise_interruption(exc: BaseException) -> None:
    """Re-raise the interruption that ``exc`` was raised while handling, if there is one.

    An interruption is a ``BaseException`` that is neither an ``Exception`` nor a
    ``GeneratorExit`` (a generator closed, which ends nothing): Ctrl-C, the CLI's SIGTERM exit.
    A clean-up that fails while one unwinds replaces it (a zip archive closed while a member is
    still being written raises ``ValueError``), and a caller that tolerates that error (an
    optional cache) would carry on as if nothing had happened.
    """
    seen: set[int] = set()
    ctx = exc.__context__
    while ctx is not None and id(ctx) not in seen:
        seen.add(id(ctx))
        if not isinstance(ctx, (Exception, GeneratorExit)):
            raise ctx
        ctx = ctx.__context__


def remove_folders(created) -> None:
    """Remove the folders :func:`make_folders` created, innermost first, while they are empty."""
    for sub in reversed(created):
        try:
            os.rmdir(sub)
        except OSError:
            break  # something else was written into it meanwhile: keep it and those above


def _check_name_length(path: Path, shown: str) -> None:
    """Refuse a file name (or its temporary file's) longer than the folder's NAME_MAX."""
    try:
        name_max = os.pathconf(path.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255  # the folder is missing (checked later) or the limit unknown
    n_bytes = len(os.fsencode(path.name))
    n_tmp = len(os.fsencode(_temporary_name(path.name)))
    if max(n_bytes, n_tmp) > name_max:
        raise OutputPathError(
            f"{shown}: file name too long ({n_bytes} bytes; the file system here takes at "
            f"most {name_max})"
        )


def _host_tag() -> str:
    """Eight hex digits of this machine's name: a folder shared over the network holds other
    machines' temporary files, whose writers' locks need not reach this one."""
    global _HOST_TAG
    if _HOST_TAG is None:
        _HOST_TAG = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
    return _HOST_TAG


_HOST_TAG: str | None = None


def _temporary_name(name: str) -> str:
    """A fresh name for the temporary file of the target ``name``, short whatever ``name``:
    ``.<name>.<host>-<pid>.<random>.tmp``, with the writer's machine (:func:`_host_tag`) and
    process, so that a file left by a writer that was killed can be told (by its lock, see
    :func:`_remove_stale`; the process id is for a person reading the folder).

    The target's full name plus a suffix would exceed NAME_MAX (255 bytes) for a name near
    the limit; its first characters still tell whose a left-over file is.  At most
    ``1 + 4 * 32 + 1 + 8 + 1 + 10 + 1 + 8 + 4`` bytes.
    """
    return f".{name[:_TMP_STEM]}.{_host_tag()}-{os.getpid()}.{secrets.token_hex(4)}.tmp"


def _lock(fd: int) -> bool:
    """Take an exclusive lock on the open file ``fd`` without waiting (``flock``, which
    processes of one machine see whatever their process-id namespace): whether it was got.
    False where the platform or the file system has no such locks."""
    try:
        import fcntl
    except ImportError:  # (not POSIX)
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # held by another (BlockingIOError), or no locks here
        return False
    return True


def _remove_stale(folder: Path, name: str) -> list[Path]:
    """Remove the temporary files of the target ``name`` (of any target whose name starts
    with the same ``_TMP_STEM`` characters) in ``folder`` that this machine wrote and whose
    writer is gone: killed (SIGKILL, the out-of-memory killer), no ``finally`` ran to remove
    them.  A writer holds a lock on its temporary file until it is renamed
    (:func:`atomic_open`): a file whose lock can be taken has no writer.  A file changed
    less than ``_STALE_AGE`` seconds ago is left (a writer may be between creating it and
    locking it).  Each folder and name is looked at once per process (stale files come from
    processes before it).  Returns the paths removed.  Best effort: a folder that cannot be
    listed, a file that cannot be opened, locked or removed is left as it is; where there
    are no locks (not POSIX, some network file systems) nothing is removed."""
    key = (os.path.abspath(folder), name[:_TMP_STEM])
    if key in _SWEPT:
        return []
    _SWEPT.add(key)
    prefix = f".{name[:_TMP_STEM]}.{_host_tag()}-"
    removed = []
    try:
        entries = [e.name for e in os.scandir(folder) if e.name.startswith(prefix)]
    except OSError:
        return []
    now = time.time()
    for entry in entries:
        if _STALE.fullmatch(entry[len(prefix) :]) is None:
            continue
        stale = folder / entry
        try:
            fd = os.open(stale, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        except OSError:  # (gone meanwhile, a folder, a link, not readable)
            continue
        try:
            if now - os.fstat(fd).st_mtime < _STALE_AGE or not _lock(fd):
                continue
            os.unlink(stale)
        except OSError:
            continue
        finally:
            os.close(fd)
        removed.append(stale)
    return removed


#: folders and name stems :func:`_remove_stale` looked at in this process
_SWEPT: set[tuple[str, str]] = set()
#: seconds since its last change before a temporary file without a writer is removed
_STALE_AGE = 10.0
#: the rest of a temporary name after ``.<name>.<host>-``: the pid, the random part, ``.tmp``
#: and, for the writers of :mod:`flyvpr.sources.writers`, the target's suffix
_STALE = re.compile(r"\d{1,10}\.[0-9a-f]{8}\.tmp(\.[^.]{1,16})?")


@contextmanager
def atomic_open(path, mode: str = "wb", **kwargs) -> Iterator:
    """Open a temporary file beside ``path``; on success rename it over ``path``.

    On any exception inside the ``with`` block (including ``KeyboardInterrupt`` and the
    CLI's SIGTERM exit) the temporary file is removed and ``path`` is left as it was.  Missing
    parent folders are created, and removed again if the write fails.  A symlink is followed
    (its target is written); a target that exists and is not a regular file is refused.  A new
    file gets ``0666 & ~umask``; an existing one keeps its mode.  The data is flushed to the
    disk (``fsync``) before the rename and the folder after it, so that a power cut leaves the
    old file or the whole new one.

    Raises
    ------
    OutputPathError
        If the target is a folder, FIFO, socket or device, or a symlink loop.
    OSError
        If writing fails (a full disk, ...): the message names ``path``.
    """
    path = Path(path)
    target = resolve_output(path)
    try:
        keep_mode = stat.S_IMODE(os.stat(target).st_mode)
    except FileNotFoundError:
        keep_mode = None  # a new file: os.open applies the umask to 0o666
    for stale in _remove_stale(target.parent, target.name):
        logger.info("removed %s, left by a writer of %s that was killed", stale, path)
    tmp = None
    lock_fd = -1
    created: list[Path] = []
    opened = False  # until then every OSError is ours: name the file being written
    try:
        for _ in range(100):
            # The name is set before the file exists, so a signal arriving at any point after
            # os.open still finds the name to remove; a random name is never another's file.
            tmp = target.parent / _temporary_name(target.name)
            try:
                fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | _O_BINARY, 0o666)
                break
            except FileExistsError:
                tmp = None
            except FileNotFoundError:
                # The folder is missing (or another writer's failure just removed a folder it
                # had created): create it and try again.
                tmp = None
                made = make_folders(target.parent)
                if not made:
                    raise
                created += made
        else:
            raise OSError(errno.EEXIST, "no free temporary name")
        # A lock on the temporary file, held until it is renamed, tells a later writer that
        # this one is alive (see _remove_stale); on a descriptor of its own, which closing
        # the file object does not release.
        lock_fd = os.dup(fd)
        _lock(lock_fd)
        if keep_mode is not None:
            os.fchmod(fd, keep_mode)
        with os.fdopen(fd, mode, **kwargs) as fh:
            opened = True
            yield fh
            # On the disk before the rename: after a power cut the target is the old file or
            # the whole new one, never a renamed empty or partial one.
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
        _sync_folder(target.parent)
    except BaseException as exc:
        if tmp is not None:
            _unlink(tmp)
        remove_folders(created)
        # Errors of the write itself carry no file name (ENOSPC, EFBIG, EIO), those of the
        # temporary file or its folders name files the user never named: name the output.
        if isinstance(exc, OSError) and (
            not opened or exc.filename is None or exc.filename == str(tmp)
        ):
            raise _named(exc, path) from None
        raise
    finally:
        if lock_fd >= 0:
            os.close(lock_fd)  # (the rename is done, or the file removed: the lock goes)


class ZipWriter(zipfile.ZipFile):
    """A ``zipfile.ZipFile`` whose ``__del__`` does nothing unless ``__init__`` finished: a
    Ctrl-C or SIGTERM inside ``__init__`` (an archive being written into
    :func:`atomic_open`'s temporary file) leaves a half-built object whose close, run when
    the traceback is freed, would print an error over the interruption (its temporary file
    goes with :func:`atomic_open`)."""

    _built = False

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._built = True

    def __del__(self):
        if self._built:
            super().__del__()


def _sync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable where the platform allows (a folder cannot be
    opened for that on Windows): best effort, the rename itself has been done."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _unlink(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _named(exc: OSError, path: Path) -> OSError:
    """The same error, with a message that names the file being written."""
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        reason = "no space left on the device"
    return OSError(exc.errno, f"cannot write {path}: {reason}")


def write_bytes_atomic(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)
    return Path(path)


def write_text_atomic(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(text)
    return Path(path)


def write_json_atomic(path, obj) -> Path:
    """Serialise ``obj`` as indented JSON and write it atomically."""
    return write_text_atomic(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")
