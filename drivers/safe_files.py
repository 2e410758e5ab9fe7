"""The one discipline for reading what a folder from anywhere holds (a dataset, a recording, an
imported public format): nothing outside the folder, nothing but regular files, bounded sizes,
strict text, bounded numbers, and every failure a :class:`DatasetError` naming the file, the
row and the field.

- Names: a name from a file (frames.csv's ``filename``) is refused when absolute, when it has
  a ``..`` part or a control character, or when it resolves (symlinks followed by name,
  nothing opened) outside the folder. The resolved path is then opened with ``O_NOFOLLOW |
  O_NONBLOCK`` and checked with ``fstat``: a FIFO, a device, a socket or a directory is
  refused at once (``companion.config.read_regular_file``, which the config file goes
  through too).
- Sizes: every file has a byte limit (a CSV field: the csv module's 128 kB); TOML nesting is
  bounded before it is parsed (``companion.toml_files.parse_toml``).
- Numbers: integers of at most 19 digits within int64, floats as decimal text of at most 40
  characters (no ``inf``, no 5,000 digits, ``nan`` only where the caller allows an unknown),
  each within the bounds its caller gives.
- Images: the size in the header (PNG IHDR, JPEG SOF) is read from the bytes and checked
  against the calibration, and the decoded size against a cap, **before** anything decodes.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import stat
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.bounded import file_kind, read_regular_file
from companion.errors import DatasetError
from companion.toml_files import decode_utf8, parse_toml

MAX_TOML_BYTES = 1 << 20  # meta.toml, calibration.toml, config.toml: a few kB
MAX_TEXT_BYTES = 1 << 20  # EuRoC's sensor.yaml and the like
MAX_CSV_BYTES = 512 << 20  # an hour of 100 Hz attitude and 6 x 50 Hz ranges: ~150 MB
MAX_IMAGE_BYTES = 64 << 20  # an encoded frame (a 4k PNG stored without compression: 25 MB)
MAX_DECODED_BYTES = 256 << 20  # what a frame may take once decoded (8192 x 8192 x 3: 192 MB)
MAX_FLOAT_CHARS = 40  # "-1.2345678901234567e-308" is 24
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
_INT = re.compile(r"[+-]?[0-9]{1,19}")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?")


# ------------------------------------------------------------------------------ numbers
def parse_int(text: str, where: str, lo: int = INT64_MIN, hi: int = INT64_MAX) -> int:
    """The integer in ``text`` (decimal, at most 19 digits) within [lo, hi]; DatasetError
    naming ``where`` (file, row, field) otherwise."""
    value = text.strip()
    if not _INT.fullmatch(value):
        raise DatasetError(f"{where}: not an integer: {_shown(text)}")
    number = int(value)
    if not lo <= number <= hi:
        raise DatasetError(f"{where}: {number} outside [{lo}, {hi}]")
    return number


def parse_float(
    text: str, where: str, lo: float = -math.inf, hi: float = math.inf, allow_nan: bool = False
) -> float:
    """The finite number in ``text`` (plain decimal or exponent notation, at most 40
    characters) within [lo, hi]; DatasetError naming ``where`` otherwise (``inf`` and words
    are refused, ``nan`` too unless ``allow_nan``: a value the writer may leave unknown)."""
    value = text.strip()
    if allow_nan and value == "nan":
        return math.nan
    if len(value) > MAX_FLOAT_CHARS or not _FLOAT.fullmatch(value):
        raise DatasetError(f"{where}: not a finite number: {_shown(text)}")
    number = float(value)
    if not math.isfinite(number) or not lo <= number <= hi:
        raise DatasetError(f"{where}: {number!r} outside [{lo}, {hi}]")
    return number


def _shown(text: str, limit: int = 40) -> str:
    """``text`` quoted, cut to ``limit`` characters, control characters escaped."""
    cut = text if len(text) <= limit else text[:limit] + "..."
    return repr(cut)


# ------------------------------------------------------------------------------ images
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel (3: palette)
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


@dataclass(frozen=True, slots=True)
class ImageHeader:
    """What an image file's header says: its size, and what it takes once decoded [bytes]
    (as OpenCV decodes it unchanged: samples per pixel x bytes per sample)."""

    kind: str
    width: int
    height: int
    decoded_bytes: int


def png_damage(data: bytes) -> str:
    """What is wrong with a PNG's chunk layout (empty when nothing): a chunk cut short, a CRC
    that does not match, no IDAT or no IEND. Checked before decoding, so that a damaged file
    is refused by name instead of reaching libpng (which prints its own errors)."""
    pos, n, idat = 8, len(data), False
    while pos + 12 <= n:
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > n:
            return f"chunk {kind!r} cut short"
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(data[pos + 4 : end - 4]) & 0xFFFFFFFF != crc:
            return f"chunk {kind!r}: CRC mismatch"
        idat = idat or kind == b"IDAT"
        if kind == b"IEND":
            return "" if idat else "no IDAT chunk"
        pos = end
    return "no IEND chunk (cut short)"


def jpeg_damage(data: bytes) -> str:
    """What is wrong with a JPEG's end (empty when nothing): a file cut short has no EOI."""
    return "" if data.rstrip(b"\x00").endswith(b"\xff\xd9") else "no end-of-image marker"


def png_header(data: bytes) -> ImageHeader | None:
    """The IHDR of a PNG (the first chunk, by the format), or None if ``data`` is not one."""
    if len(data) < 33 or not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return None
    width, height, depth, colour = struct.unpack(">IIBB", data[16:26])
    channels = 3 if colour == 3 else _PNG_CHANNELS.get(colour, 4)  # a palette decodes to BGR
    return ImageHeader("PNG", width, height, width * height * channels * max(1, depth // 8))


def jpeg_header(data: bytes) -> ImageHeader | None:
    """The size in a JPEG's start-of-frame segment (walked segment by segment from SOI), or
    None if ``data`` is not a JPEG or has no SOF before its scan."""
    if not data.startswith(b"\xff\xd8"):
        return None
    pos, n = 2, len(data)
    while pos + 4 <= n:
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # no length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if marker in _JPEG_SOF and pos + 10 <= n:
            precision, height, width, channels = struct.unpack(">BHHB", data[pos + 4 : pos + 10])
            per_pixel = 3 if channels >= 3 else 1
            return ImageHeader(
                "JPEG", width, height, width * height * per_pixel * max(1, precision // 8)
            )
        if marker == 0xDA or length < 2:  # the scan before any SOF, or a broken segment
            return None
        pos += 2 + length
    return None


def image_header(data: bytes) -> ImageHeader | None:
    """The header of a PNG or JPEG file's bytes; None for anything else."""
    return png_header(data) or jpeg_header(data)


def check_image_header(
    data: bytes, where: str, size: tuple[int, int], max_decoded: int = MAX_DECODED_BYTES
) -> ImageHeader:
    """The header of an image that may be decoded: a PNG or JPEG of exactly ``size``
    (width, height: the calibration's) whose decoded pixels fit ``max_decoded`` bytes;
    DatasetError naming ``where`` otherwise, before anything is decoded (a 1 MB PNG may
    claim 32k x 32k pixels)."""
    header = image_header(data)
    if header is None:
        raise DatasetError(f"{where}: not a PNG or JPEG file (no header to check)")
    if (header.width, header.height) != size:
        raise DatasetError(
            f"{where}: {header.kind} of {header.width} x {header.height} px, but the "
            f"calibration's camera is {size[0]} x {size[1]}: not decoded"
        )
    damage = png_damage(data) if header.kind == "PNG" else jpeg_damage(data)
    if damage:
        raise DatasetError(f"{where}: damaged {header.kind} ({damage}): not decoded")
    if header.decoded_bytes > max_decoded:
        raise DatasetError(
            f"{where}: would take {header.decoded_bytes} bytes decoded (more than "
            f"{max_decoded}): not decoded"
        )
    return header


# ------------------------------------------------------------------------------ folders
@dataclass(frozen=True, slots=True)
class CsvTable:
    """The rows of a CSV file: its header's column index, and per row its line number
    (1 = the header) and fields. ``torn``: a last line without its newline was left out."""

    name: str
    columns: dict[str, int]
    rows: list[tuple[int, list[str]]]
    torn: bool = False
    header: tuple[str, ...] = ()

    def all_rows(self) -> list[tuple[int, list[str]]]:
        """The rows with the header as the first one (for a format whose header is a
        comment that a file may lack: EuRoC's)."""
        return [(1, list(self.header)), *self.rows] if self.header else self.rows

    def has(self, column: str) -> bool:
        """Whether the header has ``column``."""
        return column in self.columns

    def where(self, line: int, column: str) -> str:
        """The text "FILE row N, COLUMN" that messages start with."""
        return f"{self.name} row {line}, {column}"

    def field(self, line: int, row: list[str], column: str) -> str:
        """The text of ``column`` in ``row`` (line ``line``); DatasetError when the row is
        shorter than its header."""
        i = self.columns[column]
        if i >= len(row):
            raise DatasetError(f"{self.where(line, column)}: missing (the row is short)")
        return row[i]


class SafeFolder:
    """A folder whose files are read under the discipline above. ``shown``: how the folder is
    named in messages (as the user gave it); names inside are resolved against its real
    path."""

    def __init__(self, path: Path) -> None:
        self.shown = path
        try:
            self.root = Path(os.path.realpath(path, strict=True))
        except (OSError, ValueError) as e:
            raise DatasetError(f"dataset folder not found: {path} ({e})") from None
        if not self.root.is_dir():
            raise DatasetError(f"dataset folder not found: {path}")

    def check_name(self, name: str, where: str) -> Path:
        """The path of ``name`` (a relative name from a file of the folder) inside the folder,
        unresolved; DatasetError naming ``where`` when it is empty, absolute, has a ``..``
        part, a NUL or a control character."""
        if not name or len(name) > 4096:
            raise DatasetError(f"{where}: empty or overlong file name")
        if any(ord(c) < 32 for c in name):
            raise DatasetError(f"{where}: control character in file name {_shown(name)}")
        if os.path.isabs(name) or name.startswith("~"):
            raise DatasetError(f"{where}: absolute file name {_shown(name)}: outside the folder")
        if ".." in Path(name).parts or ".." in name.split("\\"):
            raise DatasetError(f"{where}: '..' in file name {_shown(name)}: outside the folder")
        return self.shown / name

    def resolve(self, name: str, where: str) -> Path:
        """The real path of ``name`` inside the folder (symlinks followed by name: nothing is
        opened); DatasetError naming ``where`` when it is outside (a ``..``, an absolute
        name, a symlink out)."""
        self.check_name(name, where)
        real = Path(os.path.realpath(self.root / name))
        if real != self.root and self.root not in real.parents:
            raise DatasetError(
                f"{where}: {_shown(name)} resolves outside the dataset folder: not read"
            )
        return real

    def check_files(self, names: Sequence[str], what: str) -> None:
        """Refuse at once (DatasetError naming the ``what`` index and the name) any of
        ``names`` that resolves outside the folder or is there but not a regular file (a FIFO
        or a device as a frame): checked by name, nothing opened; missing files are left to
        the reader (an unfinished recording)."""
        for i, name in enumerate(names):
            real = self.resolve(name, f"{what} {i}")
            try:
                mode = os.stat(real).st_mode
            except OSError:
                continue
            if not stat.S_ISREG(mode):
                raise DatasetError(
                    f"{what} {i} ({name}): is {file_kind(mode)}, not a regular file: not read"
                )

    def exists(self, name: str) -> bool:
        """Whether ``name`` is there (as a link or anything else; not opened)."""
        return os.path.lexists(self.root / name)

    def read_bytes(self, name: str, max_bytes: int, where: str = "") -> bytes:
        """The bytes of the regular file ``name`` inside the folder (see the module)."""
        shown = where or f"{self.shown}/{name}"
        real = self.resolve(name, shown)
        try:  # by name first (``real`` has no links left): a device is not even opened
            mode = os.stat(real).st_mode
        except OSError:
            mode = stat.S_IFREG  # missing or unreadable: the open below says which
        if not stat.S_ISREG(mode):
            raise DatasetError(f"{shown}: is {file_kind(mode)}, not a regular file: not read")
        try:
            return read_regular_file(real, max_bytes, DatasetError, follow_symlinks=False)
        except DatasetError as e:  # the message names the real path: name it as given
            raise DatasetError(f"{shown}{str(e).removeprefix(str(real))}") from None

    def read_text(self, name: str, max_bytes: int = MAX_TEXT_BYTES) -> str:
        """The UTF-8 text of ``name`` (strict; NUL refused)."""
        return decode_utf8(self.read_bytes(name, max_bytes), f"{self.shown}/{name}", DatasetError)

    def read_toml(self, name: str) -> dict[str, Any]:
        """The TOML table of ``name`` (size and nesting bounded before parsing)."""
        return parse_toml(
            self.read_text(name, MAX_TOML_BYTES), f"{self.shown}/{name}", DatasetError
        )

    def read_csv(
        self,
        name: str,
        required: Sequence[str] = (),
        optional: bool = False,
        max_bytes: int = MAX_CSV_BYTES,
    ) -> CsvTable:
        """The rows of the CSV file ``name`` with a header holding ``required`` (DatasetError
        naming the file and the missing column otherwise). A last line without its newline is
        a row the writer did not finish: left out. ``optional``: a missing file has no rows
        (and no columns)."""
        if optional and not self.exists(name):
            return CsvTable(name, {}, [])
        text = self.read_text(name, max_bytes)
        torn = bool(text) and not text.endswith("\n")
        if torn:
            text = text[: text.rfind("\n") + 1]
        lines = _csv_rows(text, name)
        header = next(lines, None)
        if header is None:
            if required and not optional:
                raise DatasetError(f"{name}: empty (no header with {', '.join(required)})")
            return CsvTable(name, {}, [], torn)
        columns = {c.strip(): i for i, c in reversed(list(enumerate(header[1])))}
        missing = [c for c in required if c not in columns]
        if missing:
            raise DatasetError(
                f"{name} row 1 (header): missing column {missing[0]!r} "
                f"(header: {_shown(','.join(header[1]), 120)})"
            )
        return CsvTable(name, columns, list(lines), torn, tuple(header[1]))


def _csv_rows(text: str, name: str) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of each non-empty CSV row; DatasetError naming the line for a
    malformed row (an open quote, a field above the csv module's 128 kB limit). The fields'
    values are bounded by their parsers."""
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as e:
            raise DatasetError(f"{name} row {reader.line_num}: malformed CSV: {e}") from None
        if row:
            yield reader.line_num, row
