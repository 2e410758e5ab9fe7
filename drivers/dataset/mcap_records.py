"""The records of an MCAP file (https://mcap.dev/spec), read under a bounded discipline: a
file from anywhere, maybe never closed (a recorder killed mid-chunk), maybe hostile.

``scan(path)`` walks the data section record by record, decompressing each chunk (zstd or
none) within caps, and yields what our reader needs: schemas, channels, messages (each with
its :class:`Where`, so an image is read again later by its place alone), attachments and
metadata. It stops at the data section's end (DataEnd), or at the first record that is torn
or malformed: :class:`TornError` says where and why. ``closed_file(path)``: whether the file ends
with MCAP's magic (a writer that finished), which tells a torn tail (a crash: recovered)
from a damaged closed file (refused).

Every length is checked against the bytes that remain before anything is allocated: a record
may not claim more than MAX_RECORD_BYTES, a chunk more than MAX_CHUNK_BYTES once decompressed.
"""

from __future__ import annotations

import os
import stat
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import zstandard

from companion.bounded import file_kind
from companion.errors import DatasetError

MAGIC = b"\x89MCAP0\r\n"
MAX_RECORD_BYTES = 256 << 20  # a chunk of ours is 4 MB; an attachment of ours a few kB
MAX_CHUNK_BYTES = 256 << 20  # a chunk's records, decompressed
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x03, 0x04, 0x05, 0x06
OP_ATTACHMENT, OP_METADATA, OP_DATA_END = 0x09, 0x0C, 0x0F


class TornError(Exception):
    """A record that is cut short or malformed, at byte ``offset`` of the file."""

    def __init__(self, offset: int, reason: str) -> None:
        super().__init__(f"byte {offset}: {reason}")
        self.offset = offset


@dataclass(frozen=True, slots=True)
class Where:
    """A message's bytes: ``length`` bytes at ``start`` of the chunk record at file offset
    ``chunk`` (its decompressed records), or of the file itself when ``chunk`` is -1."""

    chunk: int
    start: int
    length: int


@dataclass(frozen=True, slots=True)
class Record:
    """One record the reader uses: ``kind`` is "schema", "channel", "message", "attachment"
    or "metadata"; ``fields`` its decoded fields (a message: channel_id, log_time, data);
    ``where``: a message's place."""

    kind: str
    fields: dict[str, Any]
    where: Where | None = None


class _Cursor:
    """Little-endian fields of ``data`` from ``pos`` on; TornError (at ``base`` + pos) when one
    would read past the end."""

    def __init__(self, data: bytes | memoryview, base: int, pos: int = 0) -> None:
        self.data, self.base, self.pos = data, base, pos

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise TornError(self.base + self.pos, f"a field of {n} bytes runs past its record")
        out = bytes(self.data[self.pos : self.pos + n])
        self.pos += n
        return out

    def int(self, size: int) -> int:
        value: int = struct.unpack({2: "<H", 4: "<I", 8: "<Q"}[size], self.take(size))[0]
        return value

    def text(self) -> str:
        raw = self.take(self.int(4))
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise TornError(self.base + self.pos, "a string that is not UTF-8") from None

    def strings(self) -> dict[str, str]:
        end = self.int(4) + self.pos
        if end > len(self.data):
            raise TornError(self.base + self.pos, "a map runs past its record")
        out: dict[str, str] = {}
        while self.pos < end:
            key = self.text()
            out[key] = self.text()
        return out


def open_regular(path: Path) -> IO[bytes]:
    """``path`` opened for reading: a regular file, never through a final symlink, never
    blocking (a FIFO is refused at once); DatasetError naming it otherwise."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as e:
        raise DatasetError(f"{path}: cannot read: {e.strerror or e}") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise DatasetError(f"{path}: is {file_kind(mode)}, not a regular file: not read")
    return open(fd, "rb")


def closed_file(fh: IO[bytes], size: int) -> bool:
    """Whether the file ends with MCAP's magic (its writer finished it)."""
    if size < 2 * len(MAGIC):
        return False
    fh.seek(size - len(MAGIC))
    return fh.read(len(MAGIC)) == MAGIC


def chunk_records(body: bytes, offset: int) -> bytes:
    """The decompressed records of a chunk record's content ``body`` (at file ``offset``):
    zstd or uncompressed, within MAX_CHUNK_BYTES, their CRC checked when written."""
    c = _Cursor(body, offset + 9)
    c.take(16)  # message start and end times
    size, crc, compression = c.int(8), c.int(4), c.text()
    n = c.int(8)
    data = c.take(n)
    if size > MAX_CHUNK_BYTES:
        raise TornError(
            offset, f"a chunk of {size} bytes decompressed (more than {MAX_CHUNK_BYTES})"
        )
    if compression == "zstd":
        try:  # the frame's own size claim first: it is what zstd would allocate
            if zstandard.frame_content_size(data) not in (size, -1):
                raise TornError(offset, "a zstd chunk whose frame claims another size")
            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        except zstandard.ZstdError as e:
            raise TornError(offset, f"a zstd chunk that does not decompress ({e})") from None
    elif compression == "":
        out = data
    else:
        raise TornError(offset, f"chunk compression {compression!r} (zstd or none are read)")
    if len(out) != size or (crc and zlib.crc32(out) != crc):
        raise TornError(offset, "a chunk whose size or CRC is not the one it declares")
    return out


def _inner(opcode: int, c: _Cursor, end: int, where: Where | None) -> Record | None:
    """A schema, channel or message record (its fields up to ``end``); None for others."""
    if opcode == OP_SCHEMA:
        sid, name, encoding = c.int(2), c.text(), c.text()
        return Record(
            "schema", {"id": sid, "name": name, "encoding": encoding, "data": c.take(c.int(4))}
        )
    if opcode == OP_CHANNEL:
        cid, sid, topic, encoding = c.int(2), c.int(2), c.text(), c.text()
        c.strings()
        fields = {"id": cid, "schema_id": sid, "topic": topic, "encoding": encoding}
        return Record("channel", fields)
    if opcode == OP_MESSAGE:
        channel_id, _seq, log_time, _pub = c.int(2), c.int(4), c.int(8), c.int(8)
        assert where is not None
        place = Where(where.chunk, where.start + 22, end - c.pos)
        fields = {"channel_id": channel_id, "log_time": log_time, "data": c.take(end - c.pos)}
        return Record("message", fields, place)
    return None


def records_in(data: bytes, base: int, chunk: int) -> Iterator[Record]:
    """The schema, channel and message records of a chunk's decompressed ``data`` (``base``:
    the chunk's file offset, for messages; ``chunk``: its place)."""
    pos = 0
    while pos < len(data):
        c = _Cursor(data, base, pos)
        opcode = c.take(1)[0]
        length = c.int(8)
        end = c.pos + length
        if end > len(data):
            raise TornError(base, f"a record inside the chunk runs past it ({length} bytes)")
        record = _inner(opcode, c, end, Where(chunk, c.pos, 0))
        if record is not None:
            yield record
        pos = end


def scan(fh: IO[bytes], size: int) -> Iterator[Record]:
    """The records of the data section, chunks opened; TornError at the first bad one."""
    fh.seek(0)
    if fh.read(len(MAGIC)) != MAGIC:
        raise TornError(0, "no MCAP magic at the start: not an MCAP file")
    pos = len(MAGIC)
    while pos < size:
        head = fh.read(9)
        if len(head) < 9:
            raise TornError(pos, "the file ends inside a record's header")
        opcode, length = head[0], struct.unpack("<Q", head[1:])[0]
        if length > MAX_RECORD_BYTES:
            raise TornError(pos, f"a record of {length} bytes (more than {MAX_RECORD_BYTES})")
        if pos + 9 + length > size:
            raise TornError(pos, f"the file ends inside a record of {length} bytes")
        if opcode == OP_DATA_END:
            return
        if opcode in (OP_CHUNK, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_ATTACHMENT, OP_METADATA):
            body = fh.read(length)
            yield from _outer(opcode, body, pos)
        else:
            fh.seek(length, os.SEEK_CUR)
        pos += 9 + length


def _outer(opcode: int, body: bytes, pos: int) -> Iterator[Record]:
    """The records of one data-section record (a chunk's inner ones)."""
    c = _Cursor(body, pos + 9)
    if opcode == OP_CHUNK:
        yield from records_in(chunk_records(body, pos), pos, pos)
    elif opcode == OP_ATTACHMENT:
        c.take(16)  # log and create times
        name, media = c.text(), c.text()
        yield Record("attachment", {"name": name, "media_type": media, "data": c.take(c.int(8))})
    elif opcode == OP_METADATA:
        name = c.text()
        yield Record("metadata", {"name": name, "data": c.strings()})
    else:
        record = _inner(opcode, c, len(body), Where(-1, pos + 9, 0))
        if record is not None:
            yield record


def read_at(fh: IO[bytes], where: Where, cache: dict[int, bytes]) -> bytes:
    """A message's bytes by its place (``cache``: the last chunk decompressed, by offset)."""
    if where.chunk < 0:
        fh.seek(where.start)
        return fh.read(where.length)
    if where.chunk not in cache:
        fh.seek(where.chunk)
        head = fh.read(9)
        length = struct.unpack("<Q", head[1:])[0] if len(head) == 9 else 0
        if len(head) < 9 or length > MAX_RECORD_BYTES:
            raise TornError(where.chunk, "the chunk is no longer there")
        body = fh.read(length)
        cache.clear()
        cache[where.chunk] = chunk_records(body, where.chunk)
    return cache[where.chunk][where.start : where.start + where.length]
