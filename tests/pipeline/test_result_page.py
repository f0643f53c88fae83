"""RESULT/index.html from a real (small) reconstruction: self-contained, every section present, bad
input one line. The page in a real browser: tests/bench/test_browser.py."""

import re
import shutil

import pytest
from scans import make_virtual_scan

from ntp_engine.io.errors import NtpInputError
from ntp_engine.pipeline.result_page import PAGE_FILE, VIEWER_BUNDLE, page_html, write_page
from ntp_engine.pipeline.stages import reconstruct
from ntp_engine.scanner.scan_folder import load_scan


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    scan_dir = make_virtual_scan(tmp_path_factory.mktemp("scan"), 8, 0.1, 5)
    out = tmp_path_factory.mktemp("res") / "result"
    reconstruct(load_scan(scan_dir, scan_dir / "ground_truth" / "poses.json"), out, resolution=32)
    return out


def test_the_page_holds_maps_layers_and_numbers_and_names_no_outside_file(result, tmp_path):
    copy = tmp_path / "r"
    shutil.copytree(result, copy)
    before = {p: p.stat().st_mtime_ns for p in copy.rglob("*")}
    page = write_page(copy)
    assert page == copy / PAGE_FILE
    assert {p: p.stat().st_mtime_ns for p in before} == before  # nothing else touched
    text = page.read_text()
    assert text.count("data:image/png;base64,") >= 5 + 2  # five maps, at least two coverage layers
    assert "Highlight seen" in text and "Photos per point" in text
    assert "texels.coverage" in text  # the report's numbers
    assert "No asset" in text and "ntp view RESULT --glb" in text  # no .glb: says how to get one
    # self-contained: no resource from anywhere else (the browser test also watches requests)
    assert not re.search(r"""(src|href)\s*=\s*["'](https?:|//|[^"'d#])""", text)


def test_a_glb_embeds_the_viewer(result, tmp_path):
    if not VIEWER_BUNDLE.is_file():
        pytest.skip(f"{VIEWER_BUNDLE} not built (make setup builds it where npm exists)")
    glb = tmp_path / "a.glb"
    glb.write_bytes(b"glTF" + bytes(16))
    text = page_html(result, glb)
    assert '<canvas id="ntp-canvas">' in text and 'id="ntp-light-azimuth"' in text and 'id="ntp-turntable"' in text
    assert "</script" not in text.split('<script id="ntp-data"', 1)[1].split("</script>", 1)[0]


def test_bad_input_is_one_line_naming_the_file(result, tmp_path):
    with pytest.raises(NtpInputError, match="not an ntp result"):
        write_page(tmp_path)
    with pytest.raises(NtpInputError, match="missing"):
        write_page(result, tmp_path / "none.glb")
    bad = tmp_path / "b.glb"
    bad.write_bytes(b"PK\3\4")
    with pytest.raises(NtpInputError, match="b.glb: not a binary glTF"):
        write_page(result, bad)
    assert not (tmp_path / PAGE_FILE).exists()
