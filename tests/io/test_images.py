import time

import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import read_image, write_exr, write_png


def test_exr_keeps_floats_and_png_is_8_bit(tmp_path):
    data = np.random.default_rng(0).normal(size=(5, 7, 3)).astype(np.float32) * 3
    write_exr(tmp_path / "a.exr", data)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), data)
    write_png(tmp_path / "b.png", np.array([[0.0, 0.5, 2.0, np.nan]]))
    back = read_image(tmp_path / "b.png")
    assert back.shape == (1, 4, 1)
    np.testing.assert_allclose(back[0, :, 0] * 255, [0, 128, 255, 0])


def test_unreadable_images_are_one_line_errors(tmp_path):
    bad = tmp_path / "x.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(NtpInputError, match="x.png"):
        read_image(bad)


def test_same_pixels_give_the_same_bytes(tmp_path):
    px = np.random.default_rng(0).random((8, 8, 3))
    write_exr(tmp_path / "a.exr", px)
    time.sleep(1.1)  # a later second: a write time stamped in the file would differ
    write_exr(tmp_path / "b.exr", px)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_truncated_images_are_errors_without_library_chatter(tmp_path, capfd, suffix):
    img = np.random.default_rng(1).random((64, 80, 3))
    write_png(tmp_path / "ok.png", img) if suffix == ".png" else _write_jpeg(tmp_path / "ok.jpg", img)
    data = (tmp_path / f"ok{suffix}").read_bytes()
    (tmp_path / f"half{suffix}").write_bytes(data[: len(data) // 2])
    assert read_image(tmp_path / f"ok{suffix}").shape == (64, 80, 3)
    with pytest.raises(NtpInputError, match=f"half{suffix}: truncated or corrupt image"):
        read_image(tmp_path / f"half{suffix}")  # a JPEG would decode, grey rows filled in
    assert capfd.readouterr().err == ""  # libpng's own message is not printed


def _write_jpeg(path, img):
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0], 3, oiio.UINT8))
    out.write_image((img * 255).astype(np.uint8))
    out.close()


def test_decoding_on_many_threads_leaves_stderr_where_it_was(tmp_path):
    import os
    from concurrent.futures import ThreadPoolExecutor

    good = tmp_path / "good.png"
    write_png(good, np.random.default_rng(0).random((64, 64, 3)))
    bad = tmp_path / "bad.png"
    bad.write_bytes(good.read_bytes()[:300])  # truncated: libpng complains on descriptor 2
    before = os.fstat(2)

    def read(i: int) -> bool:
        try:
            read_image(good if i % 3 else bad)
            return True
        except NtpInputError:
            return False

    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(read, range(96)))
    after = os.fstat(2)
    assert results.count(False) == 32 and (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
