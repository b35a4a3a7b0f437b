import os
import re
import subprocess
import sys

import numpy as np
import pytest

from flyvpr.large import (
    ForeignIndexError,
    LargeMapWriter,
    MapFileError,
    MultiIndexHash,
    load_index,
    open_large_map,
    save_index,
    tile_mask,
    tile_queries,
    write_large_map,
    write_tiled_map,
)
from flyvpr.large.mapfile import _TRAILER


@pytest.fixture
def codes():
    return np.random.default_rng(0).integers(0, 256, (1000, 32), dtype=np.uint8)


def test_round_trip_with_positions(tmp_path, codes):
    pos = np.random.default_rng(1).normal(size=(1000, 2))
    path = write_large_map(tmp_path / "m.fvmap", codes, pos, {"source": "test"}, chunk=300)
    m = open_large_map(path)
    assert isinstance(m.codes, np.memmap) and not m.codes.flags.writeable
    np.testing.assert_array_equal(m.codes, codes)
    np.testing.assert_array_equal(m.positions, pos)
    assert m.metadata == {"source": "test"} and m.n_places == 1000 and m.n_bits == 256
    assert len(m.map_id) == 32


def test_arrays_are_page_aligned(tmp_path, codes):
    m = open_large_map(write_large_map(tmp_path / "m.fvmap", codes))
    assert m.codes.offset % 4096 == 0 and m.positions is None


def test_writer_refuses_short_and_long(tmp_path, codes):
    path = tmp_path / "m.fvmap"
    with pytest.raises(ValueError, match="999 places appended"):
        with LargeMapWriter(path, 1000, 32) as w:
            w.append(codes[:999])
    assert not path.exists() and list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="1001 places"), LargeMapWriter(path, 1000, 32) as w:
        w.append(codes)
        w.append(codes[:1])
    assert not path.exists()


def test_writer_checks_chunks(tmp_path, codes):
    with (
        pytest.raises(ValueError, match="positions must"),
        LargeMapWriter(tmp_path / "m", 1000, 32, n_dims=2) as w,
    ):
        w.append(codes)
    with (
        pytest.raises(ValueError, match=r"uint8 of shape \(m, 32\)"),
        LargeMapWriter(tmp_path / "m", 1000, 32) as w,
    ):
        w.append(codes[:, :16])
    with pytest.raises(ValueError, match="multiple of 8"):
        LargeMapWriter(tmp_path / "m", 10, 12)


def test_a_failed_write_keeps_the_old_map(tmp_path, codes):
    path = write_large_map(tmp_path / "m.fvmap", codes)
    with pytest.raises(RuntimeError), LargeMapWriter(path, 10, 32) as w:
        w.append(codes[:5])
        raise RuntimeError("interrupted")
    np.testing.assert_array_equal(open_large_map(path).codes, codes)


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda b: b[:-5], "truncated or corrupt"),
        (lambda b: b[:10], "too short"),
        (lambda b: b"NOTAMAP!" + b[8:], "not a flyvpr map file"),
        (lambda b: b[:5000] + b[-_TRAILER.size - 400 :], "corrupt trailer"),
    ],
)
def test_damaged_files_are_refused_by_name(tmp_path, codes, damage, match):
    path = write_large_map(tmp_path / "m.fvmap", codes)
    bad = tmp_path / "bad.fvmap"
    bad.write_bytes(damage(path.read_bytes()))
    with pytest.raises(MapFileError, match=match) as info:
        open_large_map(bad)
    assert str(bad) in str(info.value)


def test_truncated_data_is_refused(tmp_path, codes):
    # cut the data but keep a valid header and trailer: the array no longer fits
    path = write_large_map(tmp_path / "m.fvmap", codes)
    raw = path.read_bytes()
    (off, length, _) = _TRAILER.unpack(raw[-_TRAILER.size :])
    header = raw[off : off + length]
    cut = 4096 + 100
    bad = raw[:cut] + header + _TRAILER.pack(cut, length, b"FLYVPRLM")
    (tmp_path / "bad").write_bytes(bad)
    with pytest.raises(MapFileError, match="truncated: array 'codes'"):
        open_large_map(tmp_path / "bad")


def test_a_deeply_nested_header_is_refused_by_name(tmp_path):
    # json.loads recurses once per "[": this header would escape as a RecursionError
    header = b"[" * 100_000 + b"]" * 100_000
    start = b"FLYVPRLM" + bytes(8)
    bad = tmp_path / "deep.fvmap"
    bad.write_bytes(start + header + _TRAILER.pack(len(start), len(header), b"FLYVPRLM"))
    with pytest.raises(MapFileError, match="corrupt header") as info:
        open_large_map(bad)
    assert str(bad) in str(info.value)


def _rewritten_header(path, change):
    """The map file at ``path`` with its JSON header passed through ``change`` (a function of
    the decoded header returning the new header's bytes)."""
    import json

    raw = path.read_bytes()
    (off, length, magic) = _TRAILER.unpack(raw[-_TRAILER.size :])
    header = change(json.loads(raw[off : off + length]))
    bad = path.with_name("bad.fvmap")
    bad.write_bytes(raw[:off] + header + _TRAILER.pack(off, len(header), magic))
    return bad


@pytest.mark.parametrize(
    ("shape", "match"),
    [
        ([2**62, 3], "truncated: array 'codes' needs bytes 4096..13835058055282167808"),
        ([3, 6148914691236517206], "truncated: array 'codes' needs bytes"),  # 2**64 + 2 bytes
        ([60.7, 32], "malformed entry for array 'codes'"),  # not read as 60
        (["60", 32], "malformed entry for array 'codes'"),
    ],
)
def test_a_header_declaring_an_impossible_shape_is_refused_by_name(tmp_path, codes, shape, match):
    # the size as int64 wrapped: negative (np.memmap raised OverflowError) or 2 bytes
    import json

    def change(header):
        header["arrays"]["codes"]["shape"] = shape
        return json.dumps(header).encode()

    bad = _rewritten_header(write_large_map(tmp_path / "m.fvmap", codes), change)
    with pytest.raises(MapFileError, match=re.escape(f"{bad}: ") + match.replace("(", r"\(")):
        open_large_map(bad)


def test_a_header_with_an_integer_past_pythons_digit_limit_is_refused_by_name(tmp_path, codes):
    def change(header):
        import json

        return json.dumps(header).replace('"version": 1', '"version": 1' + "0" * 5000).encode()

    bad = _rewritten_header(write_large_map(tmp_path / "m.fvmap", codes), change)
    with pytest.raises(MapFileError, match=re.escape(f"{bad}: corrupt header (not JSON)")):
        open_large_map(bad)


def test_a_pipe_is_no_compact_map(tmp_path):
    # its first bytes were read to tell: the read blocked for ever
    import threading

    from flyvpr.large.recording import is_compact_map

    fifo = tmp_path / "map.fifo"
    os.mkfifo(fifo)
    told = []
    reader = threading.Thread(target=lambda: told.append(is_compact_map(fifo)), daemon=True)
    reader.start()
    reader.join(10)
    assert told == [False]


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_large_map(tmp_path / "none.fvmap")


def test_index_file_round_trip(tmp_path, codes):
    m = open_large_map(write_large_map(tmp_path / "m.fvmap", codes))
    index = MultiIndexHash(radius=2).build(m.codes)
    save_index(tmp_path / "m.mih", index, m)
    back = load_index(tmp_path / "m.mih", m)
    assert back.radius == 2 and isinstance(back.places_, np.memmap)
    np.testing.assert_array_equal(back.search(codes[:3], 2)[0], index.search(codes[:3], 2)[0])
    other = open_large_map(write_large_map(tmp_path / "o.fvmap", codes[::-1]))
    with pytest.raises(ForeignIndexError, match="another map"):
        load_index(tmp_path / "m.mih", other)
    assert issubclass(ForeignIndexError, MapFileError)
    # an index of other codes is not saved as this map's, even of as many places
    with pytest.raises(ValueError, match="built over other codes than those of the map"):
        save_index(tmp_path / "x.mih", MultiIndexHash().build(codes[::-1].copy()), m)
    assert not (tmp_path / "x.mih").exists()
    # built over a copy of the map's codes: the same codes, saved
    save_index(tmp_path / "c.mih", MultiIndexHash().build(np.array(m.codes)), m)
    # the same map written again is the same map: its index fits
    again = open_large_map(write_large_map(tmp_path / "a.fvmap", codes, chunk=7))
    assert again.map_id == m.map_id
    np.testing.assert_array_equal(load_index(tmp_path / "m.mih", again).places_, back.places_)
    with pytest.raises(MapFileError, match="expected a 'map' file"):
        open_large_map(tmp_path / "m.mih")


def test_tiled_map(tmp_path):
    base = np.random.default_rng(0).integers(0, 256, (100, 32), dtype=np.uint8)
    path = write_tiled_map(tmp_path / "t.fvmap", base, 250, tile_flip=0.25, place_flip=0.0)
    m = open_large_map(path)
    assert m.n_places == 250 and m.metadata["tiled"]["n_base"] == 100
    for tile in range(3):
        rows = slice(tile * 100, min(250, tile * 100 + 100))
        np.testing.assert_array_equal(
            m.codes[rows], tile_queries(base[: rows.stop - rows.start], tile, 0.25)
        )
    mask = np.unpackbits(tile_mask(32, 1, 0.25))
    assert 0.1 < mask.mean() < 0.4
    assert not np.array_equal(tile_mask(32, 1, 0.25), tile_mask(32, 2, 0.25))


def test_tiled_map_place_noise(tmp_path):
    base = np.zeros((1000, 32), np.uint8)
    m = open_large_map(write_tiled_map(tmp_path / "t", base, 1000, tile_flip=0.0, place_flip=0.1))
    assert np.unpackbits(m.codes).mean() == pytest.approx(0.1, abs=0.01)
    with pytest.raises(TypeError, match="random_state"):
        write_tiled_map(tmp_path / "t", base, 10, random_state=None)


def test_import_flyvpr_loads_no_faiss():
    code = "import sys, flyvpr, flyvpr.large; sys.exit('faiss' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def _flip_byte(path, name, index=0):
    """Flip one byte of array ``name`` inside the file (as a disk or a copy could)."""
    from flyvpr.large.mapfile import _read_container

    header, _ = _read_container(path, "map")
    offset = header["arrays"][name]["offset"] + index
    raw = bytearray(path.read_bytes())
    raw[offset] ^= 0xFF
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("name", ["codes", "positions", "extra"])
def test_verify_finds_a_byte_changed_in_any_array(tmp_path, codes, name):
    path = tmp_path / "m.fvmap"
    with LargeMapWriter(path, n_places=1000, n_bytes=32, n_dims=2, metadata={"a": 1.5}) as w:
        w.append(codes[:600], np.zeros((600, 2)))
        w.append(codes[600:], np.ones((400, 2)))
        w.add_array("extra", np.arange(7, dtype=np.int64))
        w.add_array("empty", np.zeros((0, 3), np.float32))
    seconds = open_large_map(path).verify()  # as written: the digest matches
    assert seconds >= 0.0
    _flip_byte(path, name, index=5)
    m = open_large_map(path)  # the structure is intact: opening reads none of it
    with pytest.raises(MapFileError, match=r"m\.fvmap: the content does not match the file's"):
        m.verify()


@pytest.mark.parametrize("chunk_bytes", [1, 7, 32, 1000, 1 << 24])
@pytest.mark.parametrize("shape", [(1000, 32), (5,), (0, 3), ()])
def test_hashing_in_blocks_is_hashing_the_whole(chunk_bytes, shape):
    import hashlib

    from flyvpr.large.mapfile import _hash_rows

    array = np.arange(int(np.prod(shape)), dtype=np.int64).reshape(shape)
    digest = hashlib.sha256()
    _hash_rows(digest, array, chunk_bytes=chunk_bytes)
    assert digest.hexdigest() == hashlib.sha256(array.tobytes()).hexdigest()
