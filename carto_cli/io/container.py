"""The container format of carto's binary files: a checked preamble, a JSON header and numeric arrays.

It knows nothing of what the arrays mean (``map_file`` does). Layout (all integers little-endian)::

    offset  size  field
    0       8     magic (e.g. b"CARTOMAP")                } stable in every version, so any
    8       4     format version (uint32)                 } reader can say which version it got
    12      4     header length H (uint32)
    16      8     total file length L (uint64)
    24      4     CRC-32 of bytes 0..24
    28      H     header: UTF-8 JSON (the caller's fields, an array directory)
    28+H    D     array data: little-endian arrays, each stored, zstd or shuffle+zstd
    L-32    32    SHA-256 of bytes 0..L-32

Why this and not ``.npz`` or pickle:

- Nothing on load executes code: the header is JSON, arrays are ``np.frombuffer`` of a
  whitelisted set of plain numeric dtypes, and every offset, length and shape is checked
  against the data before use. (Pickle is never used; ``.npz`` would still need its own
  manifest, version, checksum and truncation handling, on top of zip's.)
- Failures are told apart: the stated file length reveals truncation (the common failure:
  an interrupted copy) before the checksum is even computed; the small CRC over the fixed
  preamble tells a damaged length field from a short file; the SHA-256 catches any other
  flipped bit. Each is a :class:`~carto_cli.core.errors.FormatError`; so is any inconsistency a
  forged checksum could let through (malformed JSON, an array outside the data, a bad
  dtype or shape, a decompression that does not give the declared size).
- Per-array codec, chosen at save time: the smallest of stored, zstd (level 3) and zstd of
  the byte-shuffled array (byte planes, HDF5's/Blosc's filter, which helps float columns).
  Arrays under 256 bytes are stored. zstd is smaller than zlib at any level and faster; level 9
  saved 11-15 % of the bytes for four times the time (half a second of every GMapping map's
  run), higher levels far more; shuffling helps float-heavy maps and not grid-heavy ones, so it
  is tried per array (docs/measurements.md has the figures).

Header keys written here: ``format``, ``format_version``, then the caller's fields, then
``arrays`` (name -> dtype, shape, codec, offset and length in the data, raw_length) and
``data_length``.
"""
from __future__ import annotations

import hashlib
import json
import math
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.io.atomic import atomic_output

__all__ = ["ContainerFormat", "decode", "encode", "read_bytes", "write"]

_PREAMBLE = struct.Struct("<8sIIQ")  # magic, version, header length, file length
_PREAMBLE_SIZE = _PREAMBLE.size + 4  # + CRC-32 of the preamble
_DIGEST_SIZE = 32
_MAX_HEADER = 64 << 20  # a header is a few kB; anything near this is damage, not a carto file

_ZSTD_LEVEL = 3
_MIN_COMPRESS = 256  # bytes; smaller arrays are stored
# The only dtypes a file may declare: plain numbers, no objects, no structured types.
_DTYPES = {"<f8", "<f4", "<i8", "<i4", "<u2", "|u1", "|b1"}


@dataclass(frozen=True)
class ContainerFormat:
    """One kind of file in the container: its magic, the version this carto writes and reads, and its
    name in messages and in the header's ``format`` ("map" → "not a carto map file", "carto map")."""

    magic: bytes  # 8 bytes
    version: int
    kind: str


# ---------------------------------------------------------------------------------------- writing


def _shuffle(raw: bytes | memoryview, itemsize: int) -> bytes | memoryview:
    """Byte planes: all first bytes, then all second bytes, ... (HDF5's and Blosc's shuffle filter)."""
    if itemsize == 1:
        return raw
    return np.frombuffer(raw, np.uint8).reshape(-1, itemsize).T.tobytes()


def _unshuffle(raw: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return raw
    return np.frombuffer(raw, np.uint8).reshape(itemsize, -1).T.tobytes()


def _raw_bytes(a: np.ndarray) -> memoryview:
    """The bytes of a contiguous array without copying them (``tobytes`` would double a map's cells)."""
    return a.reshape(-1).view(np.uint8).data if a.size else memoryview(b"")


def _candidates(raw: bytes | memoryview, itemsize: int) -> list[tuple[str, bytes | memoryview]]:
    """What is tried on an array besides storing it: zstd, and zstd of the byte-shuffled array for wide items;
    the smallest is kept."""
    if len(raw) < _MIN_COMPRESS:
        return []
    candidates = [("zstd", raw)]
    if itemsize >= 4:  # pose, time and index columns; grid cells (uint16) never gained from it
        candidates.append(("shuffle+zstd", _shuffle(raw, itemsize)))
    return candidates


_ZSTD_CHUNK = 1 << 22  # bytes fed to the compressor at a time


def _zstd(data: bytes | memoryview) -> bytes:
    import zstandard

    # Streamed, with the size declared up front (it goes into the frame, as a one-shot compress puts it): a
    # one-shot compress reserves the worst case, the whole input again, before it shrinks to the result. A
    # compressor per call: they are not thread-safe.
    stream = zstandard.ZstdCompressor(level=_ZSTD_LEVEL).compressobj(size=len(data))
    view = memoryview(data)
    parts = [stream.compress(view[i:i + _ZSTD_CHUNK]) for i in range(0, len(view), _ZSTD_CHUNK)]
    parts.append(stream.flush())
    return b"".join(parts)


def _smallest(raw: bytes | memoryview, packed: list[tuple[str, bytes]]) -> tuple[str, bytes | memoryview]:
    best: tuple[str, bytes | memoryview] = ("none", raw)
    for codec, blob in packed:
        if len(blob) < len(best[1]):
            best = (codec, blob)
    return best


def encode(fmt: ContainerFormat, fields: dict, arrays: dict[str, np.ndarray], jobs: int | None = None) -> bytes:
    """The whole file: ``fields`` (JSON-able) and ``arrays`` (plain numeric dtypes) in ``fmt``. The arrays are
    compressed on ``jobs`` threads (None: every core; zstd releases the GIL), each on its own: the bytes do not
    depend on ``jobs``."""
    from carto_cli.core.parallel import map_ordered

    # One array at a time, its candidates compressed side by side and only the smallest blob kept: a map's
    # cells are most of the file, and holding every array's raw bytes and every candidate at once made the
    # save the peak of a whole mapping run (dense aces: 208 MB for a 9.5 MB file).
    directory: dict[str, dict] = {}
    blobs: list[bytes | memoryview] = []
    offset = 0
    for name, array in arrays.items():
        a = np.asarray(array)
        le = a.dtype.newbyteorder("<") if a.dtype.byteorder not in ("|", "<") else a.dtype
        if le.str not in _DTYPES:
            raise TypeError(f"array {name}: dtype {a.dtype} cannot be stored in a {fmt.kind} file")
        raw = _raw_bytes(np.ascontiguousarray(a, dtype=le))
        candidates = _candidates(raw, le.itemsize)
        packed = map_ordered(lambda cand: _zstd(cand[1]), candidates, jobs)
        codec, blob = _smallest(raw, [(c, b) for (c, _), b in zip(candidates, packed)])
        del candidates, packed
        directory[name] = {"dtype": le.str, "shape": list(a.shape), "codec": codec,
                           "offset": offset, "length": len(blob), "raw_length": len(raw)}
        blobs.append(blob)
        offset += len(blob)
    header = {
        "format": f"carto {fmt.kind}",
        "format_version": fmt.version,
        **fields,
        "arrays": directory,
        "data_length": offset,
    }
    header_bytes = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    total = _PREAMBLE_SIZE + len(header_bytes) + offset + _DIGEST_SIZE
    preamble = _PREAMBLE.pack(fmt.magic, fmt.version, len(header_bytes), total)
    body = b"".join([preamble, struct.pack("<I", zlib.crc32(preamble)), header_bytes, *blobs])
    return body + hashlib.sha256(body).digest()


def write(path: str | Path, fmt: ContainerFormat, fields: dict, arrays: dict[str, np.ndarray],
          jobs: int | None = None) -> Path:
    """Encode (on ``jobs`` threads), then write ``path`` atomically (an interrupted save leaves the old file, or
    none)."""
    path = Path(path)
    data = encode(fmt, fields, arrays, jobs)
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return path


# ---------------------------------------------------------------------------------------- reading


def read_bytes(path: Path, fmt: ContainerFormat) -> bytes:
    """The file's bytes; a :class:`CartoError` naming the file when it cannot be read."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise CartoError(f"no such {fmt.kind} file", path) from None
    except IsADirectoryError:
        raise CartoError(f"is a directory, not a {fmt.kind} file", path) from None
    except OSError as e:
        raise CartoError(f"cannot read {fmt.kind} file: {e.strerror or e}", path) from None


def decode(data: bytes, path: Path, fmt: ContainerFormat) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays) of a whole file; :class:`FormatError` for anything but a good file of ``fmt``'s version."""
    kind = fmt.kind
    n = len(data)
    magic = fmt.magic
    if n == 0:
        raise FormatError(f"empty file, not a carto {kind} file", path)
    if n < len(magic):
        if magic.startswith(data):
            raise FormatError(f"truncated {kind} file ({n} bytes)", path)
        raise FormatError(f"not a carto {kind} file", path)
    if data[: len(magic)] != magic:
        raise FormatError(f"not a carto {kind} file", path)
    if n < 12:
        raise FormatError(f"truncated {kind} file ({n} bytes)", path)
    (version,) = struct.unpack_from("<I", data, 8)
    if version != fmt.version:
        raise FormatError(f"{kind} file version {version}, this carto reads {fmt.version}", path)
    if n < _PREAMBLE_SIZE:
        raise FormatError(f"truncated {kind} file ({n} bytes)", path)
    _, _, header_length, total = _PREAMBLE.unpack_from(data, 0)
    (crc,) = struct.unpack_from("<I", data, _PREAMBLE.size)
    if zlib.crc32(data[: _PREAMBLE.size]) != crc:
        raise FormatError("corrupt: damaged file preamble", path)
    if n < total:
        raise FormatError(f"truncated {kind} file: {n} of {total} bytes", path)
    if n > total:
        raise FormatError(f"corrupt: {n - total} unexpected bytes after the end of the {kind}", path)
    if header_length > _MAX_HEADER or _PREAMBLE_SIZE + header_length + _DIGEST_SIZE > total:
        raise FormatError("malformed header: impossible header length", path)
    body_end = total - _DIGEST_SIZE
    if hashlib.sha256(memoryview(data)[:body_end]).digest() != data[body_end:]:
        raise FormatError("corrupt: checksum mismatch", path)

    data_start = _PREAMBLE_SIZE + header_length
    try:
        header = json.loads(data[_PREAMBLE_SIZE:data_start].decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise FormatError(f"malformed header: {e}", path) from None
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), dict):
        raise FormatError("malformed header: no array directory", path)
    if header.get("format_version") != fmt.version:
        raise FormatError("malformed header: format version differs from the preamble's", path)
    data_length = body_end - data_start
    if header.get("data_length") != data_length:
        raise FormatError("malformed header: data length disagrees with the file", path)
    payload = memoryview(data)[data_start:body_end]
    arrays = {name: _array(name, spec, payload, path) for name, spec in header["arrays"].items()}
    return header, arrays


def _array(name: str, spec, payload: memoryview, path: Path) -> np.ndarray:
    def bad(what: str) -> FormatError:
        return FormatError(f"malformed header: array {name!r}: {what}", path)

    if not isinstance(spec, dict):
        raise bad("not a description")
    def size(key: str) -> int:
        v = spec.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise bad("bad offset or length")
        return v

    dtype_str, shape, codec = spec.get("dtype"), spec.get("shape"), spec.get("codec")
    if dtype_str not in _DTYPES:
        raise bad(f"dtype {dtype_str!r} not allowed")
    if not (isinstance(shape, list) and len(shape) <= 4
            and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
        raise bad(f"bad shape {shape!r}")
    offset, length, raw_length = size("offset"), size("length"), size("raw_length")
    if offset + length > len(payload):
        raise bad("extends past the data")
    dtype = np.dtype(dtype_str)
    expected = dtype.itemsize * math.prod(shape)
    if raw_length != expected:
        raise bad(f"{raw_length} bytes for shape {shape} of {dtype_str}")
    blob = payload[offset: offset + length]
    if codec == "none":
        if length != raw_length:
            raise bad("stored length differs from its size")
        raw = bytes(blob)
    elif codec in ("zstd", "shuffle+zstd"):
        import zstandard

        packed = bytes(blob)
        try:
            if zstandard.frame_content_size(packed) != raw_length:
                raise bad("compressed size header differs from the declared size")
            raw = zstandard.ZstdDecompressor().decompress(packed, max_output_size=raw_length)
        except zstandard.ZstdError as e:
            raise bad(f"cannot decompress: {e}") from None
        if len(raw) != raw_length:
            raise bad("decompressed size differs from the declared one")
        if codec == "shuffle+zstd":
            raw = _unshuffle(raw, dtype.itemsize)
    else:
        raise bad(f"unknown codec {codec!r}")
    array = np.frombuffer(raw, dtype=dtype).reshape(shape)
    if dtype_str == "|b1" and array.size and array.view(np.uint8).max() > 1:
        raise bad("boolean values other than 0 and 1")
    native = array.astype(dtype.newbyteorder("="), copy=False)
    if not native.flags.writeable:
        native = native.copy()
    return native
