"""Fixtures of the fault battery (``tests/faults/faults.py``): small datasets and damaged files.

Every builder writes into a folder it is given and returns what the cases need; nothing is
downloaded and nothing outside that folder is touched.  The model-file tools play an attacker
who knows the format: they rewrite a file with recomputed checksums, so only the loader's own
checks stand between the damage and a loaded model.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import stat
import struct
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

#: frames per traverse in the small datasets
N_FRAMES = 12
#: first RobotCar-style time stamp (UNIX microseconds, 16 digits)
T0_US = 1418132416000000


# -- images and datasets -----------------------------------------------------------------------
def frames(n: int, seed: int, size=(32, 64), noise: float = 0.0) -> np.ndarray:
    """``n`` distinct uint8 gray frames: smooth random blobs, plus optional noise."""
    rng = np.random.default_rng(seed)
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    out = np.empty((n, h, w), np.uint8)
    base = np.random.default_rng(1000)  # places are the same whatever the seed
    for i in range(n):
        cy, cx = base.uniform(0, h, 4), base.uniform(0, w, 4)
        img = sum(
            np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * (h / 4) ** 2))
            for y, x in zip(cy, cx, strict=True)
        )
        img = img / img.max() * 200 + rng.normal(0, noise, (h, w))
        out[i] = np.clip(img, 0, 255).astype(np.uint8)
    return out


def write_folder(folder: Path, images: np.ndarray, pattern: str = "{i:03d}.png") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, img in enumerate(images):
        path = folder / pattern.format(i=i)
        Image.fromarray(img).save(path)
        paths.append(path)
    return paths


def generic_dataset(root: Path, n: int = N_FRAMES, pattern: str = "{i:03d}.png") -> Path:
    """``root/reference`` and ``root/query``: frame i of both shows place i."""
    write_folder(root / "reference", frames(n, 0), pattern)
    write_folder(root / "query", frames(n, 1, noise=8.0), pattern)
    return root


def positions_csv(root: Path, n: int = N_FRAMES, bom: bool = False, latin1: bool = False) -> Path:
    """``root/positions.csv`` placing frame i of both traverses at (10 i, 0) metres."""
    rows = ["traverse,filename,x,y"]
    for role in ("reference", "query"):
        rows += [f"{role},{i:03d}.png,{10.0 * i},0.0" for i in range(n)]
    text = "\n".join(rows) + "\n"
    data = text.encode("utf-8")
    if bom:
        data = b"\xef\xbb\xbf" + data
    if latin1:  # a comment-like extra column value with an e-acute in Latin-1
        data = data.replace(b"x,y", b"x,y,note", 1).replace(b".0\n", b".0,\xe9t\xe9\n")
    path = root / "positions.csv"
    path.write_bytes(data)
    return path


def nordland_dataset(root: Path, n: int = N_FRAMES) -> Path:
    write_folder(root / "summer", frames(n, 0), "images-{i:05d}.png")
    write_folder(root / "winter", frames(n, 1, noise=8.0), "images-{i:05d}.png")
    return root


def vprbench_dataset(root: Path, n: int = N_FRAMES, gt_header_shape=None) -> Path:
    write_folder(root / "ref", frames(n, 0))
    write_folder(root / "query", frames(n, 1, noise=8.0))
    path = root / "ground_truth.npy"
    if gt_header_shape is None:
        np.save(path, np.eye(n, dtype=bool))
    else:  # a 100-byte file whose header claims a huge matrix
        header = {"descr": "|b1", "fortran_order": False, "shape": tuple(gt_header_shape)}
        with open(path, "wb") as fh:
            np.lib.format.write_array_header_1_0(fh, header)
            fh.write(b"\x01" * 16)
    return root


def robotcar_run(root: Path, name: str, stamps_us=None, pose_stamp_text=None) -> Path:
    """A tiny run in the RobotCar layout: 8 gray Bayer PNGs and gps/ins.csv (10 m/s north)."""
    from flyvpr.datasets.robotcar import INS_COLUMNS

    centre = root / name / "stereo" / "centre"
    centre.mkdir(parents=True)
    stamps = stamps_us if stamps_us is not None else [T0_US + k * 1_000_000 for k in range(8)]
    for i, s in enumerate(stamps):
        Image.fromarray(np.full((8, 8), 40 + 20 * i, np.uint8)).save(centre / f"{s}.png")
    (root / name / "gps").mkdir()
    with open(root / name / "gps" / "ins.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(INS_COLUMNS)
        for k in range(-1, 10):
            t = T0_US + k * 1_000_000
            stamp = pose_stamp_text if (pose_stamp_text and k == 4) else t
            w.writerow(
                [stamp, "GOOD", 51.7, -1.2, 100, 5735000 + 10 * k, 620000, 0, "30U"] + [0] * 6
            )
    return root / name


def float_tiff(path: Path, values: np.ndarray) -> Path:
    Image.fromarray(values.astype(np.float32)).save(path)
    return path


def png16(path: Path, value: int, shape=(32, 64)) -> Path:
    Image.fromarray(np.full(shape, value, np.uint16)).save(path)
    return path


def png_declaring(path: Path, width: int, height: int) -> Path:
    """A valid-looking PNG whose header declares ``width x height`` with one tiny data block."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
    data += chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b"")
    path.write_bytes(data)
    return path


# -- file state --------------------------------------------------------------------------------
def snapshot(root: Path) -> dict:
    """Path -> (kind, mode, content hash or link target) of everything under ``root``."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = os.lstat(p)
            if stat.S_ISLNK(st.st_mode):
                out[str(p)] = ("link", os.readlink(p))
            elif stat.S_ISREG(st.st_mode):
                digest = hashlib.sha256(p.read_bytes()).hexdigest()
                out[str(p)] = ("file", stat.S_IMODE(st.st_mode), digest)
            elif stat.S_ISDIR(st.st_mode):
                out[str(p)] = ("dir",)
            else:
                out[str(p)] = ("special", stat.S_IFMT(st.st_mode))
    return out


def leftovers(root: Path) -> list[str]:
    """Temporary files (``*.tmp``) anywhere under ``root``."""
    return sorted(str(p) for p in Path(root).rglob("*.tmp"))


# -- model files, as an attacker who knows the format would rewrite them ----------------------
def read_model(path: Path) -> tuple[dict, dict]:
    """(meta, arrays) of a model file, without the loader's checks."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    return meta, arrays


def write_model(path: Path, meta: dict, arrays: dict, *, bomb=None) -> Path:
    """Write ``meta`` and ``arrays`` as a model file with a recomputed content checksum and
    file checksum, i.e. a file that passes every integrity check.

    ``bomb=(name, shape)`` adds a deflated member ``name`` holding a float32 ``.npy`` array
    of ``shape`` made of zeros: about 1 MB on disk per GB it expands to.
    """
    from flyvpr.modelio import _checksum

    meta = dict(meta)
    meta.pop("checksum", None)
    meta["checksum"] = _checksum(meta, arrays)
    members = []
    payload = {"__meta__": np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays}
    for key, value in payload.items():
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
        data = buf.getvalue()
        members.append((key + ".npy", data, 0, zlib.crc32(data), len(data)))
    if bomb is not None:
        members.append(_bomb_member(*bomb))
    blob = _zip(members, b"0" * 64)
    digest = hashlib.sha256(blob[:-64]).hexdigest().encode()
    path.write_bytes(blob[:-64] + digest)
    return path


def _zip(members, comment: bytes) -> bytes:
    """A plain ZIP archive (no zip64: every member under 4 GB) of pre-encoded members
    ``(name, data, method, crc, uncompressed_size)``; method 0 stored, 8 deflated."""
    out, central = bytearray(), bytearray()
    for name, data, method, crc, size in members:
        raw = name.encode()
        offset = len(out)
        sizes = (crc, len(data), size, len(raw))
        local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0x21, *sizes, 0)
        out += local + raw + data
        entry = struct.pack("<IHHHHHH", 0x02014B50, 20, 20, 0, method, 0, 0x21)
        central += entry + struct.pack("<IIIHHHHHII", *sizes, 0, 0, 0, 0, 0, offset) + raw
    start = len(out)
    out += central
    n = len(members)
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central), start, len(comment))
    out += end + comment
    return bytes(out)


def _bomb_member(name: str, shape):
    """A deflated ``.npy`` member of float32 zeros of ``shape`` (made in about a second).

    Each 1 MB block of zeros is compressed with a full flush, which resets the compressor,
    so every block compresses to the same bytes: the stream is one block repeated.
    """
    buf = io.BytesIO()
    header = {"descr": "<f4", "fortran_order": False, "shape": tuple(shape)}
    np.lib.format.write_array_header_1_0(buf, header)
    head = buf.getvalue()
    n_data = 4 * int(np.prod(shape))
    block = 1 << 20
    n_blocks, tail = divmod(n_data, block)
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    first = comp.compress(head) + comp.flush(zlib.Z_FULL_FLUSH)
    zeros = bytes(block)
    repeated = comp.compress(zeros) + comp.flush(zlib.Z_FULL_FLUSH)
    last = comp.compress(bytes(tail)) + comp.flush()
    data = first + repeated * n_blocks + last
    crc = zlib.crc32(head)
    for _ in range(n_blocks):
        crc = zlib.crc32(zeros, crc)
    crc = zlib.crc32(bytes(tail), crc)
    return name, data, 8, crc, len(head) + n_data


def bomb_model(honest: Path, out: Path, n_columns: int = 1 << 22) -> Path:
    """The honest model with ``frontend/weights_`` replaced by a deflated entry whose header
    and data claim (64, n_columns) float32: 1 GB for the default, about 1 MB on disk."""
    meta, arrays = read_model(honest)
    del arrays["frontend/weights_"]
    return write_model(out, meta, arrays, bomb=("frontend/weights_.npy", (64, n_columns)))
