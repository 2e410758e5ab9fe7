"""Calibration boards: the spec, the printable image and sub-pixel corner detection (pure).

Two kinds, written on the command line as

- ``chessboard:COLSxROWS:SQUARE_M`` — COLS x ROWS **inner corners** (where four squares meet,
  OpenCV's ``patternSize``; a board of 10 x 7 squares has 9 x 6 inner corners), squares of side
  SQUARE_M metres. Every corner must be seen: a view is all or nothing.
- ``charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]`` — COLS x ROWS **squares** (OpenCV's
  ``CharucoBoard`` size), ArUco markers of side MARKER_M in the white squares, from the
  dictionary DICT (default ``DICT_5X5_100``). Any part of the board is usable: each inner
  corner is identified by its neighbouring markers, so partial views near the image border —
  where the distortion is strongest — still count.

Board frame (metres): x along the columns, y along the rows, z = 0 on the board. A chessboard's
origin is its first inner corner; a ChArUco board's origin is its outer top-left corner
(OpenCV's ``getChessboardCorners``). A view's corners are ``object_points_m`` (N, 3) in this
frame and ``image_points_px`` (N, 2) in distorted pixel coordinates (pixel centre (0, 0) at
0.0, 0.0, as in :mod:`companion.geometry.camera`).

Printable image: ``board_image`` draws the board at ``px_per_m`` with a white margin; a board
point (X, Y) [m] lies at the continuous image coordinate ``origin_px + px_per_m * (X, Y)``
(pixel centres at integers). Corner detection: ``cv2.findChessboardCornersSB`` (the
sector-based detector, Duda & Frese, BMVC 2018) with a fallback to ``findChessboardCorners`` +
``cornerSubPix``; ChArUco through ``cv2.aruco.CharucoDetector``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import CalibrationError
from companion.types import F64

I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]

BoardKind = Literal["chessboard", "charuco"]
DEFAULT_DICTIONARY = "DICT_5X5_100"

_SPEC_HELP = (
    "chessboard:COLSxROWS:SQUARE_M (inner corners, e.g. chessboard:9x6:0.025) or "
    "charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT] (squares, e.g. charuco:11x8:0.03:0.022)"
)


@dataclass(frozen=True, slots=True)
class BoardSpec:
    """A planar calibration board. See the module docstring for cols/rows and the frame."""

    kind: BoardKind
    cols: int  # inner corners (chessboard) or squares (charuco) along x
    rows: int  # inner corners (chessboard) or squares (charuco) along y
    square_m: float  # side of one square [m]
    marker_m: float = 0.0  # side of an ArUco marker [m] (charuco only)
    dictionary: str = DEFAULT_DICTIONARY  # ArUco dictionary name (charuco only)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.square_m) and self.square_m > 0):
            raise CalibrationError(f"board: square size must be > 0 m, got {self.square_m}")
        if self.kind == "chessboard":
            if min(self.cols, self.rows) < 3:
                raise CalibrationError(
                    f"board: a chessboard needs at least 3x3 inner corners, got "
                    f"{self.cols}x{self.rows}"
                )
            if self.cols == self.rows:
                raise CalibrationError(
                    f"board: a square chessboard ({self.cols}x{self.rows} inner corners) is "
                    "ambiguous under a 90 degree turn; use different column and row counts"
                )
        else:
            if min(self.cols, self.rows) < 3:
                raise CalibrationError(
                    f"board: a ChArUco board needs at least 3x3 squares, got "
                    f"{self.cols}x{self.rows}"
                )
            if not 0 < self.marker_m < self.square_m:
                raise CalibrationError(
                    f"board: the marker ({self.marker_m} m) must be smaller than the square "
                    f"({self.square_m} m)"
                )
            if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
                raise CalibrationError(
                    f"board: unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50, "
                    "DICT_5X5_100, DICT_6X6_250)"
                )

    @staticmethod
    def parse(text: str) -> BoardSpec:
        """Parse a command-line spec (module docstring); raises CalibrationError when bad."""
        parts = text.strip().split(":")
        kind = parts[0].lower()
        size = re.fullmatch(r"(\d+)[xX](\d+)", parts[1]) if len(parts) > 1 else None
        try:
            numbers = [float(p) for p in parts[2:4] if not p.startswith("DICT")]
        except ValueError:
            numbers = []
        if kind == "chessboard" and len(parts) == 3 and size and len(numbers) == 1:
            return BoardSpec("chessboard", int(size[1]), int(size[2]), numbers[0])
        if kind == "charuco" and len(parts) in (4, 5) and size and len(numbers) == 2:
            dictionary = parts[4].upper() if len(parts) == 5 else DEFAULT_DICTIONARY
            return BoardSpec(
                "charuco", int(size[1]), int(size[2]), numbers[0], numbers[1], dictionary
            )
        raise CalibrationError(f"board: cannot read {text!r}; expected {_SPEC_HELP}")

    def text(self) -> str:
        """The spec in command-line form (the inverse of :meth:`parse`)."""
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"
        size = f"{self.cols}x{self.rows}"
        return f"charuco:{size}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    @property
    def squares(self) -> tuple[int, int]:
        """Squares (across, down) of the printed board."""
        if self.kind == "chessboard":
            return self.cols + 1, self.rows + 1
        return self.cols, self.rows

    def corner_points_m(self) -> F64:
        """Every inner corner of the board, (N, 3) in the board frame [m], indexed by corner id
        (row-major: id = row * corners_across + column)."""
        if self.kind == "charuco":
            return np.asarray(self.aruco_board().getChessboardCorners(), dtype=np.float64)
        c, r = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        xy = np.stack([c.ravel(), r.ravel()], axis=1) * self.square_m
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    def aruco_board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard`` of a charuco spec (OpenCV >= 4.6 pattern)."""
        if self.kind != "charuco":
            raise CalibrationError("board: not a ChArUco board")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.cols, self.rows), self.square_m, self.marker_m, dictionary
        )


@dataclass(frozen=True, slots=True)
class BoardImage:
    """A printable board: ``image`` (H, W) uint8 (black 0, white 255); a board point (X, Y) [m]
    is at the continuous pixel coordinate ``origin_px + px_per_m * (X, Y)``."""

    image: U8
    px_per_m: float
    origin_px: F64  # (2,) [px]


def board_image(spec: BoardSpec, px_per_m: float, margin_squares: float = 1.0) -> BoardImage:
    """Draw the board with whole pixels per square and a white margin of ``margin_squares``.

    The square is rounded to whole pixels, so the printed square is
    ``round(square_m * px_per_m) / px_per_m`` metres (measure it after printing anyway).
    """
    sq = int(round(spec.square_m * px_per_m))
    if sq < 8:
        raise CalibrationError(
            f"board: {sq} px per square at this resolution; raise the resolution (dpi)"
        )
    ppm = sq / spec.square_m
    margin = int(round(margin_squares * sq))
    nx, ny = spec.squares
    if spec.kind == "chessboard":
        j, i = np.meshgrid(np.arange(nx * sq) // sq, np.arange(ny * sq) // sq)
        squares = np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)
        img = np.full((ny * sq + 2 * margin, nx * sq + 2 * margin), 255, dtype=np.uint8)
        img[margin : margin + ny * sq, margin : margin + nx * sq] = squares
        # the first inner corner is one square in from the board's outer corner
        origin = np.array([margin + sq - 0.5, margin + sq - 0.5])
    else:
        size = (nx * sq + 2 * margin, ny * sq + 2 * margin)
        img = np.asarray(spec.aruco_board().generateImage(size, marginSize=margin), np.uint8)
        origin = np.array([margin - 0.5, margin - 0.5])
    return BoardImage(img, ppm, origin)


@dataclass(frozen=True, slots=True)
class BoardView:
    """The corners found in one image: ``image_points_px`` (N, 2) [px, distorted],
    ``object_points_m`` (N, 3) [m, board frame], ``corner_ids`` (N,) into corner_points_m()."""

    name: str
    image_points_px: F64
    object_points_m: F64
    corner_ids: I64


@dataclass(frozen=True, slots=True)
class DetectorOptions:
    """How board corners are found (not part of the service config: CLI flags)."""

    min_charuco_corners: int = 6  # fewer ChArUco corners in a view: the view is not used
    exhaustive: bool = True  # findChessboardCornersSB: try harder on difficult views (slower)


@dataclass(slots=True)
class BoardDetector:
    """Finds a board's inner corners in images, with sub-pixel accuracy."""

    spec: BoardSpec
    opts: DetectorOptions = field(default_factory=DetectorOptions)
    _corners_m: F64 = field(init=False)
    _charuco: Any = field(init=False, default=None)

    def __post_init__(self) -> None:
        self._corners_m = self.spec.corner_points_m()
        if self.spec.kind == "charuco":
            self._charuco = cv2.aruco.CharucoDetector(self.spec.aruco_board())

    def detect(self, image: U8, name: str = "") -> BoardView | None:
        """The board's corners in ``image`` ((H, W) grey or (H, W, 3) BGR), or None."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.spec.kind == "chessboard":
            uv = self._chessboard(gray)
            if uv is None:
                return None
            ids = np.arange(len(uv), dtype=np.int64)
        else:
            found = self._charuco_corners(gray)
            if found is None:
                return None
            uv, ids = found
        return BoardView(name, uv, self._corners_m[ids].copy(), ids)

    def _chessboard(self, gray: U8) -> F64 | None:
        size = (self.spec.cols, self.spec.rows)
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
        if self.opts.exhaustive:
            flags |= cv2.CALIB_CB_EXHAUSTIVE
        ok, corners = cv2.findChessboardCornersSB(gray, size, flags=flags)
        if ok:
            return np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, size, flags=flags)
        if not ok:
            return None
        uv = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
        # the refinement window must stay inside one square: half the smallest corner spacing
        grid = uv.reshape(self.spec.rows, self.spec.cols, 2)
        spacing = min(
            float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
            float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()),
        )
        half = int(np.clip(spacing / 2 - 1, 2, 11))
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
        refined = cv2.cornerSubPix(gray, uv.reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
        return np.asarray(refined, dtype=np.float64).reshape(-1, 2)

    def _charuco_corners(self, gray: U8) -> tuple[F64, I64] | None:
        corners, ids, _, _ = self._charuco.detectBoard(gray)
        if ids is None or len(ids) < max(self.opts.min_charuco_corners, 4):
            return None
        ids_i = np.asarray(ids, dtype=np.int64).ravel()
        board = self._charuco.getBoard()
        if board.checkCharucoCornersCollinear(ids.astype(np.int32)):
            return None  # a single row of corners constrains no homography
        return np.asarray(corners, dtype=np.float64).reshape(-1, 2), ids_i
