"""The marker board's layout, its PDF as a printer draws it, and its layout file's bad forms."""

import json

import cv2
import numpy as np
import pypdfium2
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.register.board_poses import detect_corners
from ntp_engine.scanner.board import (
    INK_ALBEDO,
    PAPER_ALBEDO,
    PAPERS,
    PRINT_MARGIN_MM,
    board_for_paper,
    read_board,
    write_board,
)

DPI = 300


@pytest.mark.parametrize("paper", list(PAPERS))
def test_each_paper_holds_its_squares_inside_the_printable_area(paper):
    board = board_for_paper(paper)
    w, h = PAPERS[paper]
    assert board.squares[0] * board.square_mm <= w - 2 * PRINT_MARGIN_MM
    assert board.squares[1] * board.square_mm <= h - 2 * PRINT_MARGIN_MM
    # one more square would not fit: the board uses the paper
    assert (board.squares[0] + 1) * board.square_mm > w - 2 * PRINT_MARGIN_MM
    corners = board.corner_points()
    assert corners.shape == ((board.squares[0] - 1) * (board.squares[1] - 1), 3)
    assert np.allclose(corners.mean(0), 0.0) and np.all(corners[:, 2] == 0)  # centred, on the plane


def test_the_ink_is_opencvs_own_board():
    board = board_for_paper("A4")
    page = board.paper_image(0.5)  # albedo per 0.5 mm texel over the paper
    margin = ((np.array(board.paper_mm) - np.array(board.squares) * board.square_mm) / 2 / 0.5).round().astype(int)
    squares = page[margin[1] : page.shape[0] - margin[1], margin[0] : page.shape[1] - margin[0]]
    theirs = board.opencv().generateImage((squares.shape[1], squares.shape[0]), marginSize=0, borderBits=1)
    white = (squares - INK_ALBEDO) / (PAPER_ALBEDO - INK_ALBEDO)
    differ = np.abs(white - theirs / 255.0) > 0.5
    assert differ.mean() < 0.01  # edge texels only (OpenCV rounds each edge to a whole pixel)


def test_the_pdf_prints_the_board_at_its_size(tmp_path):
    board = board_for_paper("A4")
    layout = write_board(tmp_path / "board.pdf", board)
    assert read_board(layout) == board
    page = pypdfium2.PdfDocument(tmp_path / "board.pdf")[0]
    w_pt, h_pt = page.get_size()
    assert abs(w_pt * 25.4 / 72 - 297.0) < 0.01 and abs(h_pt * 25.4 / 72 - 210.0) < 0.01
    grey = cv2.cvtColor(page.render(scale=DPI / 72).to_numpy(), cv2.COLOR_RGB2GRAY)
    ids, px = detect_corners(grey, board)
    assert len(ids) == len(board.corner_points())  # every corner of the printed page found
    # where the layout says each corner is on the paper (the squares centred on it), in page pixels
    x, y = 1e3 * board.corner_points()[ids, 0], 1e3 * board.corner_points()[ids, 1]
    expected = np.stack([297.0 / 2 + x, 210.0 / 2 - y], 1) / 25.4 * DPI - 0.5
    assert np.abs(px - expected).max() * 25.4 / DPI < 0.1  # mm: the print is the layout


def test_a_damaged_or_foreign_layout_is_one_line_naming_the_file(tmp_path):
    good = board_for_paper("A4").to_json()
    cases = {
        "truncated.json": json.dumps(good)[:40],
        "poses.json": json.dumps({"0000.png": np.eye(4).tolist()}),
        "version.json": json.dumps({**good, "version": 7}),
        "dictionary.json": json.dumps({**good, "dictionary": "DICT_9X9_1"}),
        "marker.json": json.dumps({**good, "marker_mm": 31.0}),
        "squares.json": json.dumps({**good, "squares": [9.5, 6]}),
        "missing.json": json.dumps({k: v for k, v in good.items() if k != "square_mm"}),
        "too_many.json": json.dumps({**good, "squares": [40, 30], "dictionary": "DICT_4X4_50"}),
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(NtpInputError) as err:
            read_board(tmp_path / name)
        line = str(err.value)
        assert name in line and "\n" not in line, line
    with pytest.raises(NtpInputError, match="does not exist"):
        read_board(tmp_path / "absent.json")


def test_writing_never_replaces_a_file_that_is_not_a_board(tmp_path):
    board = board_for_paper("letter")
    mine = tmp_path / "notes.pdf"
    mine.write_bytes(b"%PDF- the user's own")
    with pytest.raises(NtpInputError, match="not overwritten"):
        write_board(mine, board)
    assert mine.read_bytes() == b"%PDF- the user's own" and not (tmp_path / "notes.json").exists()
    with pytest.raises(NtpInputError, match="ending in .pdf"):
        write_board(tmp_path / "board.png", board)
    layout = write_board(tmp_path / "board.pdf", board)
    write_board(tmp_path / "board.pdf", board_for_paper("A3"))  # a board's own files: a re-run replaces them
    assert read_board(layout).paper == "A3"
