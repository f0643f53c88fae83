"""The marker board: a printed ChArUco board the object stands on, which gives every photo that sees
it a metric camera pose without structure from motion (OpenCV's ``cv2.aruco``).

Convention: the *board frame* is metric (metres), its origin the centre of the squares, x along the
paper's long side, y along the short side (up on the printed page), z out of the paper — the side the
object stands on; the support plane is z = 0. Poses are camera-from-board 4x4 (OpenCV axes), pixel
centres at integers (the device file's convention). Layout lengths in the file are millimetres.

A board is described by its layout file (``board.json``, written beside the PDF by ``ntp board``):
the paper, the dictionary, the grid of squares and the square and marker sizes as printed. If the
printer scaled the page, the user writes the square size they measured (``square_mm``; the marker
scales with it). Every problem with the file is a one-line ``NtpInputError`` naming it.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path, write_text_atomic
from ..io.errors import NtpInputError
from ..io.input_file import MAX_BYTES, regular_file

FORMAT = "ntp marker board"
VERSION = 1
# paper sizes (mm, long side first) and the margin a printer leaves blank (mm)
PAPERS: dict[str, tuple[float, float]] = {"A4": (297.0, 210.0), "A3": (420.0, 297.0), "letter": (279.4, 215.9)}
PRINT_MARGIN_MM = 10.0
# A square of 30 mm with a 22 mm marker: a marker cell (22/6 mm) spans >= 3 pixels at the scanner's
# working distance (0.31 m) in photos a quarter of the device's width (0.53 mm a pixel), head-on,
# and the A4 board still has 9 x 6 squares (40 inner corners) around an object 15 cm across
SQUARE_MM = 30.0
MARKER_MM = 22.0
# 4x4 bits: the largest cells for a marker's size; 250 ids cover an A3 board (59 markers)
DICTIONARY = "DICT_4X4_250"
PAPER_ALBEDO = 0.85  # white office paper (the virtual scanner's board)
INK_ALBEDO = 0.04  # black laser toner


@dataclass(frozen=True)
class Board:
    """A ChArUco board as printed: ``squares`` (along x, along y), lengths in millimetres."""

    paper: str
    paper_mm: tuple[float, float]
    squares: tuple[int, int]
    square_mm: float
    marker_mm: float
    dictionary: str = DICTIONARY

    @property
    def size_m(self) -> tuple[float, float]:
        """The squares' extent (x, y) in metres."""
        return (self.squares[0] * self.square_mm * 1e-3, self.squares[1] * self.square_mm * 1e-3)

    def opencv(self):
        """The board as OpenCV's ``cv2.aruco.CharucoBoard`` (lengths in metres, its own frame)."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square_mm * 1e-3, self.marker_mm * 1e-3, dictionary)

    def corner_points(self) -> np.ndarray:
        """The inner chessboard corners ``(N, 3)`` in the board frame (metres), in OpenCV's corner-id
        order (row by row from the page's top left)."""
        return self.to_board_frame(np.asarray(self.opencv().getChessboardCorners(), dtype=np.float64))

    def to_board_frame(self, opencv_points: np.ndarray) -> np.ndarray:
        """Points ``(..., 3)`` of OpenCV's board frame (origin the squares' top left, y down the page)
        in the board frame (origin their centre, y up, z out of the paper)."""
        w, h = self.size_m
        p = np.asarray(opencv_points, dtype=np.float64)
        return np.stack([p[..., 0] - w / 2, h / 2 - p[..., 1], -p[..., 2]], -1)

    def ink(self) -> np.ndarray:
        """The black rectangles of the print ``(K, 4)`` as (x0, y0, x1, y1) in millimetres from the
        squares' top left, y down the page: the dark squares, then each marker's black cells (runs
        along a row merged). One description serves the PDF and the virtual scanner's texture."""
        import cv2

        b = self.opencv()
        nx, ny = self.squares
        s, bits = self.square_mm, b.getDictionary().markerSize + 2
        rects = [(i * s, j * s, (i + 1) * s, (j + 1) * s) for j in range(ny) for i in range(nx) if (i + j) % 2 == 0]
        cell = self.marker_mm / bits
        for corners, marker in zip(b.getObjPoints(), b.getIds().ravel(), strict=True):
            x0, y0 = 1e3 * np.asarray(corners)[0, :2]
            image = cv2.aruco.generateImageMarker(b.getDictionary(), int(marker), bits)
            for r, row in enumerate(image < 128):
                edges = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])))
                for a, e in zip(edges[::2], edges[1::2], strict=True):
                    rects.append((x0 + a * cell, y0 + r * cell, x0 + e * cell, y0 + (r + 1) * cell))
        return np.array(rects)

    def albedo(self, xy: np.ndarray, texel_mm: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
        """The printed board's albedo at board-frame points ``xy (N, 2)`` (metres) and whether each
        lies on the paper ``(N,)``: ``paper_image`` sampled bilinearly (the virtual scanner's support)."""
        from scipy import ndimage

        image = self.paper_image(texel_mm)
        pw, ph = self.paper_mm
        x_mm, y_mm = 1e3 * np.asarray(xy)[:, 0], 1e3 * np.asarray(xy)[:, 1]
        u, v = (x_mm + pw / 2) / texel_mm - 0.5, (ph / 2 - y_mm) / texel_mm - 0.5
        albedo = ndimage.map_coordinates(image, [v, u], order=1, mode="nearest")
        return albedo, (np.abs(x_mm) <= pw / 2) & (np.abs(y_mm) <= ph / 2)

    def paper_image(self, texel_mm: float) -> np.ndarray:
        """The printed page's albedo ``(rows, cols)`` float32, ``texel_mm`` a texel, row 0 the page's
        top (+y), the squares centred: each texel paper and ink in the share the ink covers it (4 x 4
        samples a texel). The virtual scanners' board texture (engine and Cycles)."""
        return _paper_image(self, texel_mm)

    def to_json(self) -> dict:
        """The layout file's content."""
        return {
            "format": FORMAT,
            "version": VERSION,
            **asdict(self),
            "frame": "origin at the squares' centre, x along the long side, y up the page, z out of the paper; metres",
        }


@functools.lru_cache(maxsize=4)
def _paper_image(board: Board, texel_mm: float) -> np.ndarray:
    """``Board.paper_image``, made once per board and texel (the renderer asks for it per chunk)."""
    fine = texel_mm / 4
    pw, ph = board.paper_mm
    nx, ny = 4 * int(round(pw / texel_mm)), 4 * int(round(ph / texel_mm))
    x0 = (pw - board.squares[0] * board.square_mm) / 2
    y0 = (ph - board.squares[1] * board.square_mm) / 2
    ink = np.zeros((ny, nx), dtype=np.float32)
    for a, b, c, d in board.ink():
        rows = slice(int(round((y0 + b) / fine)), int(round((y0 + d) / fine)))
        ink[rows, int(round((x0 + a) / fine)) : int(round((x0 + c) / fine))] = 1
    share = ink.reshape(ny // 4, 4, nx // 4, 4).mean((1, 3))
    image = (PAPER_ALBEDO + (INK_ALBEDO - PAPER_ALBEDO) * share).astype(np.float32)
    image.setflags(write=False)  # shared by every caller
    return image


def board_for_paper(paper: str) -> Board:
    """The board ``ntp board --size`` prints: as many ``SQUARE_MM`` squares as fit the paper's
    printable area (``PRINT_MARGIN_MM`` each side), landscape."""
    if paper not in PAPERS:
        raise NtpInputError(None, f"--size {paper}: have {', '.join(PAPERS)}")
    w, h = PAPERS[paper]
    squares = (int((w - 2 * PRINT_MARGIN_MM) // SQUARE_MM), int((h - 2 * PRINT_MARGIN_MM) // SQUARE_MM))
    return Board(paper, (w, h), squares, SQUARE_MM, MARKER_MM)


def read_board(path: Path) -> Board:
    """The layout file ``path`` (``board.json``); a one-line ``NtpInputError`` naming it when it is
    unreadable, not an ntp board layout, or describes a board OpenCV cannot make."""
    regular_file(path, MAX_BYTES["board"])
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise NtpInputError(path, f"cannot read the board layout ({err})") from None
    return board_from_json(data, path)


def board_from_json(data: object, path: Path | None = None) -> Board:
    """The board a layout's content describes (``Board.to_json``, e.g. a virtual scan's capture
    record); a one-line ``NtpInputError`` naming ``path`` when it is not one OpenCV can make."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise NtpInputError(path, f'not an ntp board layout (no "format": "{FORMAT}"; ntp board writes one)')
    if data.get("version") != VERSION:
        raise NtpInputError(path, f"board layout version {data.get('version')!r}; this ntp reads {VERSION}")
    try:
        board = Board(
            paper=str(data["paper"]),
            paper_mm=_numbers(data["paper_mm"], 2, float),
            squares=_numbers(data["squares"], 2, int),
            square_mm=float(data["square_mm"]),
            marker_mm=float(data["marker_mm"]),
            dictionary=str(data["dictionary"]),
        )
    except KeyError as err:
        raise NtpInputError(path, f"board layout misses {err.args[0]!r}") from None
    except (TypeError, ValueError) as err:
        raise NtpInputError(path, f"board layout: {err}") from None
    _check(board, path)
    return board


def _numbers(value: object, count: int, kind: type) -> tuple:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != count:
        raise ValueError(f"expected {count} numbers, got {value!r}")
    out = tuple(kind(v) for v in value)
    if kind is int and any(o != v for o, v in zip(out, value, strict=True)):
        raise ValueError(f"expected whole numbers, got {value!r}")
    return out


def _check(board: Board, path: Path | None) -> None:
    import cv2

    if not board.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, board.dictionary):
        raise NtpInputError(path, f"unknown marker dictionary {board.dictionary!r} (OpenCV's, e.g. {DICTIONARY})")
    if min(board.squares) < 2:
        raise NtpInputError(path, f"squares {list(board.squares)}: need at least 2 x 2")
    if not (np.isfinite(board.square_mm) and 0 < board.marker_mm < board.square_mm):
        raise NtpInputError(path, f"need 0 < marker_mm ({board.marker_mm}) < square_mm ({board.square_mm})")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    markers = board.squares[0] * board.squares[1] // 2
    if markers > len(dictionary.bytesList):
        raise NtpInputError(path, f"{markers} markers, but {board.dictionary} has {len(dictionary.bytesList)}")


def write_board(pdf: Path, board: Board) -> Path:
    """The printable board ``pdf`` (vector, the paper's size, 1:1) and its layout file beside it
    (``pdf`` with ``.json``); returns the layout's path. Each appears complete or not at all; a file
    there already is replaced only when the layout beside it is an ntp board's (a re-run)."""
    pdf = Path(pdf)
    if pdf.suffix.lower() != ".pdf":
        raise NtpInputError(pdf, "the board is written as a PDF: give a name ending in .pdf")
    layout = pdf.with_suffix(".json")
    if pdf.exists() or layout.exists():
        try:
            read_board(layout)
        except NtpInputError:
            there = pdf if pdf.exists() else layout
            raise NtpInputError(there, "exists and is not an ntp board's; not overwritten (another --out)") from None
    with atomic_path(pdf) as tmp:
        tmp.write_bytes(board_pdf(board))
    write_text_atomic(layout, json.dumps(board.to_json(), indent=1))
    return layout


def board_pdf(board: Board) -> bytes:
    """A one-page PDF of ``board`` at 1:1: the squares centred on the paper, a 100 mm bar to check
    the print's scale, and a line saying what it is."""
    pt = 72.0 / 25.4  # PDF points a millimetre
    pw, ph = board.paper_mm
    x_left = (pw - board.squares[0] * board.square_mm) / 2
    y_top = (ph - board.squares[1] * board.square_mm) / 2
    ops = ["0 g"]
    for x0, y0, x1, y1 in board.ink():  # PDF's y runs up from the bottom of the page
        x, y = (x_left + x0) * pt, (ph - y_top - y1) * pt
        ops.append(f"{x:.4f} {y:.4f} {(x1 - x0) * pt:.4f} {(y1 - y0) * pt:.4f} re f")
    bar_y = max(ph - y_top - board.squares[1] * board.square_mm - 6.0, 3.0)
    ops.append(f"{x_left * pt:.4f} {bar_y * pt:.4f} {100 * pt:.4f} {1.0 * pt:.4f} re f")
    text = (
        f"ntp marker board {board.paper}: {board.squares[0]} x {board.squares[1]} squares of {board.square_mm:g} mm, "
        f"{board.dictionary}. Print at 100% (no fit to page): the bar measures 100 mm."
    )
    text = text.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")
    ops.append(f"BT /F1 7 Tf {(x_left + 104) * pt:.4f} {bar_y * pt:.4f} Td ({text}) Tj ET")
    content = "\n".join(ops).encode("ascii")
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (
            f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {pw * pt:.4f} {ph * pt:.4f}] "
            "/Resources << /Font << /F1 5 0 R >> >> /Contents 4 0 R >>"
        ).encode("ascii"),
        b"<< /Length %d >>\nstream\n" % len(content) + content + b"\nendstream",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica >>",
    ]
    out = bytearray(b"%PDF-1.4\n")
    offsets = []
    for i, body in enumerate(objects, 1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % i + body + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objects) + 1)
    out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
    out += b"trailer\n<< /Size %d /Root 1 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (len(objects) + 1, xref)
    return bytes(out)
