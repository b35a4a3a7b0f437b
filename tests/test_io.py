"""Tests of flyvpr._io: atomic writes, where outputs may go, permissions, errors naming files."""

import errno
import json
import os
import stat

import pytest

from flyvpr import _io
from flyvpr._io import (
    OutputPathError,
    atomic_open,
    check_output_path,
    make_folders,
    remove_folders,
    write_json_atomic,
    write_text_atomic,
)
from flyvpr.images import IMAGE_EXTENSIONS


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def test_new_file_follows_umask(tmp_path):
    old = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "a.txt", "x")
        os.umask(0o077)
        write_text_atomic(tmp_path / "b.txt", "x")
    finally:
        os.umask(old)
    assert _mode(tmp_path / "a.txt") == 0o644
    assert _mode(tmp_path / "b.txt") == 0o600


def test_existing_file_keeps_its_mode(tmp_path):
    path = tmp_path / "a.json"
    path.write_text("{}")
    path.chmod(0o640)
    write_json_atomic(path, {"x": 1})
    assert _mode(path) == 0o640 and '"x": 1' in path.read_text()


def test_symlink_is_followed_and_kept(tmp_path):
    target = tmp_path / "target.txt"
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    write_text_atomic(link, "new")
    assert link.is_symlink() and target.read_text() == "new"


def test_dangling_symlink_writes_its_target(tmp_path):
    link = tmp_path / "link.txt"
    link.symlink_to(tmp_path / "later.txt")
    write_text_atomic(link, "new")
    assert (tmp_path / "later.txt").read_text() == "new" and link.is_symlink()


@pytest.mark.parametrize("kind", ["folder", "fifo", "device", "loop"])
def test_non_regular_targets_are_refused(tmp_path, kind):
    path = tmp_path / "out"
    if kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        path.symlink_to("/dev/null")
    else:
        path.symlink_to(path)
    with pytest.raises(OutputPathError, match="out"):
        write_text_atomic(path, "x")
    with pytest.raises(OutputPathError, match="--out"):
        check_output_path(path, what="--out")
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))


def test_failure_inside_the_block_leaves_the_old_file(tmp_path):
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_open(path, "w") as fh:
            fh.write("half")
            raise RuntimeError("boom")
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_full_disk_is_named_and_cleaned(tmp_path, monkeypatch):
    real_fdopen = os.fdopen

    class Full:
        def __init__(self, fh):
            self.fh = fh

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

    monkeypatch.setattr(_io.os, "fdopen", lambda fd, *a, **k: Full(real_fdopen(fd, *a, **k)))
    with pytest.raises(OSError, match=r"cannot write .*a\.json: no space left") as info:
        write_json_atomic(tmp_path / "a.json", {"x": 1})
    assert info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_output_that_is_an_input_is_refused(tmp_path):
    (tmp_path / "in").mkdir()
    image = tmp_path / "in" / "1.png"
    image.write_bytes(b"x")
    link = tmp_path / "alias.png"
    link.symlink_to(image)
    for out in (image, link, tmp_path / "in" / "." / "1.png"):
        with pytest.raises(OutputPathError, match="is an input of this run"):
            check_output_path(out, [image], what="--out")
    assert check_output_path(tmp_path / "new.json", [image]) == tmp_path / "new.json"


def test_output_into_a_folder_of_images_the_run_reads_is_refused(tmp_path):
    # a later run on that folder would refuse the file (an image folder holds images only)
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "0001.png").write_bytes(b"x")
    (tmp_path / "route.csv").write_text("frame,x,y\n")
    bag = tmp_path / "bag2"  # a folder without images (a ROS 2 bag's): not refused
    bag.mkdir()
    (bag / "metadata.yaml").write_text("")
    for inputs in ([frames / "0001.png"], [frames], [tmp_path / "route.csv", frames]):
        for out in (frames / "r.json", frames / "." / "r.map", frames / "x.png", frames / "s/r"):
            with pytest.raises(OutputPathError, match=f"--out {out} would go into {frames}, a "):
                check_output_path(out, inputs, what="--out", image_extensions=IMAGE_EXTENSIONS)
            # without the image suffixes, no folder is one of images
            assert check_output_path(out, inputs, what="--out") == frames / out.relative_to(frames)
    # inputs given as a generator are read once only: still refused
    with pytest.raises(OutputPathError, match="a folder of images this run reads"):
        check_output_path(frames / "r.json", iter([frames]), image_extensions=IMAGE_EXTENSIONS)
    inputs = [frames / "0001.png", tmp_path / "route.csv"]
    assert check_output_path(tmp_path / "r.json", inputs, image_extensions=IMAGE_EXTENSIONS)
    kept = check_output_path(bag / "where.csv", [bag], image_extensions=IMAGE_EXTENSIONS)
    assert kept == bag / "where.csv"


def test_output_folder_checks(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputPathError, match="not a folder"):
        check_output_path(tmp_path / "file" / "a.json")
    with pytest.raises(OutputPathError, match=r"file is not a folder"):
        check_output_path(tmp_path / "file" / "b" / "a.json")
    with pytest.raises(OutputPathError, match="too long"):
        check_output_path(tmp_path / "a" / ("b" * 256) / "a.json")
    with pytest.raises(OutputPathError, match=r"too long \(256 bytes; .* at most 255\)"):
        check_output_path(tmp_path / ("x" * 256), what="--out")


@pytest.mark.parametrize("name", ["r" * 245 + ".json", "r" * 255, "é" * 127])
def test_a_name_up_to_name_max_is_written_atomically(tmp_path, monkeypatch, name):
    # The temporary file's name once was the target's plus 14 bytes: over NAME_MAX (255).
    seen = []
    real_open = os.open
    monkeypatch.setattr(_io.os, "open", lambda p, *a: seen.append(p) or real_open(p, *a))
    assert check_output_path(tmp_path / name, what="--out") == tmp_path / name
    write_json_atomic(tmp_path / name, {"x": 1})
    assert [p.name for p in tmp_path.iterdir()] == [name]
    tmp, folder = seen  # the temporary file, then the folder synced after the rename
    assert folder == tmp_path
    assert tmp.parent == tmp_path and tmp.name.startswith("." + name[:32] + ".")
    assert len(os.fsencode(tmp.name)) <= 1 + 4 * 32 + 1 + 8 + 4


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name an fd")
def test_the_data_is_on_the_disk_before_the_rename_and_the_folder_after(tmp_path, monkeypatch):
    # A power cut between a rename and the page cache's write-back could leave the target
    # renamed but empty: the temporary file is fsynced, whole, before the rename, and the
    # folder (which holds the rename) after it.
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        path = os.readlink(f"/proc/self/fd/{fd}")
        events.append(("fsync", os.path.basename(path), os.fstat(fd).st_size))
        real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", os.path.basename(src), os.path.basename(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(_io.os, "fsync", fsync)
    monkeypatch.setattr(_io.os, "replace", replace)
    out = tmp_path / "r.bin"
    _io.write_bytes_atomic(out, b"x" * 5000)
    (kind, tmp, size), (kind2, src, dst), (kind3, folder, _) = events
    assert (kind, kind2, kind3) == ("fsync", "replace", "fsync")
    assert tmp == src and tmp.endswith(".tmp") and size == 5000 and dst == "r.bin"
    assert folder == tmp_path.name

    # The file's own fsync failing fails the write (the target keeps its old contents) ...
    def refuse(fd):
        raise OSError(errno.EIO, "I/O error")

    monkeypatch.setattr(_io.os, "fsync", refuse)
    with pytest.raises(OSError, match="cannot write .*r.bin: I/O error"):
        _io.write_bytes_atomic(out, b"y")
    assert out.read_bytes() == b"x" * 5000 and [p.name for p in tmp_path.iterdir()] == ["r.bin"]

    # ... a folder that cannot be synced does not: the rename is done (a file system that
    # refuses a folder's fsync, a platform that cannot open a folder).
    def files_only(fd):
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "Invalid argument")
        real_fsync(fd)

    monkeypatch.setattr(_io.os, "fsync", files_only)
    _io.write_bytes_atomic(out, b"z")
    assert out.read_bytes() == b"z"
    real_open = os.open

    def no_folders(p, flags, *a):
        if os.path.isdir(p):
            raise PermissionError(errno.EACCES, "Permission denied", str(p))
        return real_open(p, flags, *a)

    monkeypatch.setattr(_io.os, "open", no_folders)
    _io.write_bytes_atomic(out, b"w")
    assert out.read_bytes() == b"w"


def test_missing_folders_are_created_only_when_the_file_is_written(tmp_path):
    out = tmp_path / "a" / "b" / "c" / "r.json"
    assert check_output_path(out, what="--out") == out
    assert list(tmp_path.iterdir()) == []  # checked, not created
    write_json_atomic(out, {"x": 1})
    assert json.loads(out.read_text()) == {"x": 1}
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.json"]


def test_a_failed_write_removes_the_folders_it_created(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "kept.txt").write_text("x")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_open(tmp_path / "a" / "b" / "c" / "r.json", "w") as fh:
            fh.write("half")
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "kept.txt"]


def test_folders_made_for_a_flushed_writer_and_removed_again(tmp_path):
    created = make_folders(tmp_path / "a" / "b")
    assert created == [tmp_path / "a", tmp_path / "a" / "b"]
    assert make_folders(tmp_path / "a" / "b") == []  # nothing new: nothing to undo
    (tmp_path / "a" / "other").write_text("x")
    remove_folders(created)  # b goes; a holds another file and stays
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "other"]


def test_read_only_folder(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("running as root: permissions are not enforced")
        with pytest.raises(OutputPathError, match="not writable"):
            check_output_path(folder / "a.json")
    finally:
        folder.chmod(0o755)


@pytest.mark.skipif(os.name != "posix", reason="flock: a writer's lock on POSIX")
def test_a_killed_writer_s_temporary_file_is_removed_by_the_next_write(
    tmp_path, caplog, monkeypatch
):
    # A writer killed with SIGKILL (or by the out-of-memory killer) runs no cleanup: its
    # temporary file stays.  The next write of the same target removes it (its writer's lock
    # is gone), and only it.
    import fcntl
    import hashlib
    import signal
    import socket
    import subprocess
    import sys
    import time

    # (the machine's tag: 8 hex digits of its name's hash)
    assert _io._host_tag() == hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
    monkeypatch.setattr(_io, "_SWEPT", set())
    out = tmp_path / "map.fvmap"
    code = (
        "import sys, time; from flyvpr import _io\n"
        "with _io.atomic_open(sys.argv[1], 'wb') as fh:\n"
        "    fh.write(b'x' * 1000); fh.flush(); print('writing', flush=True); time.sleep(60)\n"
    )
    child = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE)
    try:
        assert child.stdout.readline() == b"writing\n"
        (left,) = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
        assert f".{_io._host_tag()}-{child.pid}." in left.name
        # alive, it holds the lock: a writer of the same target leaves its file alone
        old = time.time() - 12  # (unchanged for 12 s: over the 10 s a fresh file is left)
        os.utime(left, (old, old))
        _io.write_bytes_atomic(out, b"first")
        assert left.exists() and out.read_bytes() == b"first"
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
    assert left.exists()  # (killed: nothing ran to remove it)
    # a locked file (a live writer, here this test), a file changed a moment ago, another
    # target's, another machine's, a name that only looks like one and a folder are kept
    name = left.name
    locked = tmp_path / name.replace(f"-{child.pid}.", "-1.")
    young = tmp_path / name.replace(f"-{child.pid}.", "-2.")
    other = tmp_path / name.replace(".map.fvmap.", ".other.fvmap.")
    elsewhere = tmp_path / name.replace(f".{_io._host_tag()}-", ".00000000-")
    odd = tmp_path / (name + "x")
    folder = tmp_path / name.replace(f"-{child.pid}.", "-3.")
    for p in (locked, young, other, elsewhere, odd):
        p.write_bytes(b"keep")
    folder.mkdir()
    for p in (left, locked, other, elsewhere, odd, folder):
        os.utime(p, (old, old))
    holder = os.open(locked, os.O_RDONLY)
    fcntl.flock(holder, fcntl.LOCK_EX)
    monkeypatch.setattr(_io, "_SWEPT", set())
    try:
        with caplog.at_level("INFO", logger="flyvpr"):
            _io.write_bytes_atomic(out, b"new")
    finally:
        os.close(holder)
    assert out.read_bytes() == b"new" and not left.exists() and folder.is_dir()
    assert all(p.read_bytes() == b"keep" for p in (locked, young, other, elsewhere, odd))
    removed = [r.getMessage() for r in caplog.records if "left by a writer" in r.getMessage()]
    assert removed == [f"removed {left}, left by a writer of {out} that was killed"]
    # a folder and name are looked at once per process: a stale file made since stays
    os.utime(locked, (old, old))
    _io.write_bytes_atomic(out, b"again")
    assert locked.exists()


def test_an_archive_interrupted_while_it_is_built_is_dropped_quietly(monkeypatch):
    # A Ctrl-C or SIGTERM inside ZipFile.__init__, between its taking the file and its
    # setting up (here: reading the file's name interrupted), leaves a half-built archive;
    # plain ZipFile's __del__ then fails over it (an error printed after the interruption's
    # message), ZipWriter's does nothing.
    import gc
    import io
    import sys
    import zipfile

    class Interrupted(io.BytesIO):
        @property
        def name(self):
            raise KeyboardInterrupt

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: seen.append(u.exc_type))
    for cls in (zipfile.ZipFile, _io.ZipWriter):
        with pytest.raises(KeyboardInterrupt):
            cls(Interrupted(), "w")
        gc.collect()
    assert seen == [AttributeError]  # (the plain one's only)
    with _io.ZipWriter(io.BytesIO(), "w") as zf:  # a whole one closes as ZipFile does
        zf.writestr("a.txt", "x")
    assert zf.fp is None


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to count descriptors")
def test_a_write_that_fails_early_closes_no_descriptor_of_others(tmp_path, monkeypatch):
    # a write that fails before its temporary file exists (here: no free temporary name)
    # leaves every descriptor of the process open (the lock's is opened with the file only)
    (tmp_path / ".taken.tmp").write_bytes(b"")
    monkeypatch.setattr(_io, "_temporary_name", lambda name: ".taken.tmp")
    before = sorted(os.listdir("/proc/self/fd"))
    with pytest.raises(OSError, match="out.bin: .*no free temporary name"):
        _io.write_bytes_atomic(tmp_path / "out.bin", b"x")
    assert sorted(os.listdir("/proc/self/fd")) == before
    os.fstat(2)  # (stderr among them)


def test_a_taken_temporary_name_is_drawn_again_a_hundred_times(tmp_path, monkeypatch):
    # a name another writer holds is drawn afresh; after 100 draws the write gives up
    (tmp_path / ".taken.tmp").write_bytes(b"")
    drawn = []
    monkeypatch.setattr(_io, "_temporary_name", lambda name: drawn.append(name) or ".taken.tmp")
    with pytest.raises(OSError, match="no free temporary name"):
        _io.write_bytes_atomic(tmp_path / "out.bin", b"x")
    assert drawn == ["out.bin"] * 100 and not (tmp_path / "out.bin").exists()
    names = iter([".taken.tmp"] * 99 + [".free.tmp"])
    monkeypatch.setattr(_io, "_temporary_name", lambda name: next(names))
    _io.write_bytes_atomic(tmp_path / "out.bin", b"x")  # (the 100th draw is free)
    assert (tmp_path / "out.bin").read_bytes() == b"x"


def test_a_failed_rename_names_the_output_not_the_temporary_file(tmp_path, monkeypatch):
    # os.replace's error names the temporary file, which the user never named
    def refuse(src, dst):
        raise OSError(errno.EACCES, "Permission denied", str(src))

    monkeypatch.setattr(_io.os, "replace", refuse)
    out = tmp_path / "out.json"
    with pytest.raises(OSError) as info:
        write_json_atomic(out, {"a": 1})
    assert info.value.strerror == f"cannot write {out}: Permission denied"
    assert os.listdir(tmp_path) == []


@pytest.mark.skipif(os.name != "posix", reason="flock: a writer's lock on POSIX")
def test_a_temporary_file_unchanged_for_exactly_the_age_is_stale(tmp_path, monkeypatch):
    # a file without a writer is removed once it has not changed for 10 s, not before
    assert _io._STALE_AGE == 10.0
    name = f".out.bin.{_io._host_tag()}-7.0123abcd.tmp"
    left = tmp_path / name
    for age, kept in ((_io._STALE_AGE - 0.5, True), (_io._STALE_AGE, False)):
        left.write_bytes(b"old")
        os.utime(left, (1_000_000.0, 1_000_000.0))
        monkeypatch.setattr(_io, "_SWEPT", set())
        monkeypatch.setattr(_io.time, "time", lambda age=age: 1_000_000.0 + age)
        _io.write_bytes_atomic(tmp_path / "out.bin", b"new")
        assert left.exists() is kept


def test_json_is_written_indented_by_two_and_ends_with_a_newline(tmp_path):
    obj = {"b": [1, 2], "a": {"c": None}}
    write_json_atomic(tmp_path / "a.json", obj)
    assert (tmp_path / "a.json").read_text() == json.dumps(obj, indent=2) + "\n"


def test_helpers_for_kinds_same_files_folders_and_interruptions(tmp_path):
    # the kind of a character device, named in the refusal of such a target
    assert _io._kind(stat.S_IFCHR | 0o666) == "a device"
    # two names of a file that does not exist (yet) are compared as resolved paths
    a, b = tmp_path / "no" / "x.json", tmp_path / "no" / ".." / "no" / "x.json"
    assert a != b  # (pathlib keeps "..": only the resolved paths are the same)
    assert _io._same_file(a, b) and not _io._same_file(a, tmp_path / "no" / "y.json")
    # a folder of images named twice is one folder; a file that is not an image, none
    images = tmp_path / "frames"
    images.mkdir()
    (images / "0001.png").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("x")
    exts = tuple(IMAGE_EXTENSIONS)
    assert _io._image_folders([images, images, tmp_path / "notes.txt"], exts) == [images]
    # an interruption anywhere in an error's context chain is raised again; none: nothing
    try:
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as stop:
                raise ValueError("closing the archive failed") from stop
        except ValueError as closing:
            raise OSError("the cache is optional") from closing
    except OSError as exc:
        with pytest.raises(KeyboardInterrupt):
            _io.raise_interruption(exc)
    try:
        try:
            raise ValueError("first")
        except ValueError as first:
            raise OSError("second") from first
    except OSError as exc:
        assert _io.raise_interruption(exc) is None
        exc.__context__.__context__ = exc  # (a cycle ends the walk too)
        assert _io.raise_interruption(exc) is None
