import pytest

from ntp_engine.bench import scan


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_one_small_size_end_to_end_with_a_plot(tmp_path):
    r = scan.run([(6, 16)], plot=tmp_path / "p.png", work=tmp_path / "w", known_poses=True)
    (row,) = r["sizes"]
    assert row["photos"] == 6 and row["resolution"] == 16 and 0 < row["relit_ssim"] <= 1
    assert (tmp_path / "p.png").is_file()
