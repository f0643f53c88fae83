import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.scanner.pattern import (
    QUANTUM,
    named_pattern,
    patterns_agree,
    quantise,
    read_pattern_file,
    write_pattern_file,
)


def test_written_patterns_are_quantised_and_agree_with_the_original(tmp_path):
    p = np.random.default_rng(0).random((6, 3))
    write_pattern_file(tmp_path / "p.csv", p)
    back = read_pattern_file(tmp_path / "p.csv", 6)
    np.testing.assert_allclose(back, quantise(p), atol=1e-8)
    assert patterns_agree(back, p) and not patterns_agree(back, p + 0.6 * QUANTUM)
    assert not patterns_agree(back, p[:5])


def test_bad_pattern_files_name_the_file(tmp_path):
    with pytest.raises(NtpInputError, match="none.csv: does not exist"):
        read_pattern_file(tmp_path / "none.csv", 4)
    np.savetxt(tmp_path / "short.csv", np.ones((3, 3)), delimiter=",")
    with pytest.raises(NtpInputError, match=r"short.csv: expected 4x3"):
        read_pattern_file(tmp_path / "short.csv", 4)
    np.save(tmp_path / "big.npy", np.full((4, 3), 1.5))
    with pytest.raises(NtpInputError, match=r"big.npy: values must be in \[0, 1\]"):
        read_pattern_file(tmp_path / "big.npy", 4)


def test_named_patterns():
    s = load_scanner()
    assert (named_pattern("full_on", s) == 1).all()
    point = named_pattern("point", s)
    assert point.sum() == 3 and point.max() == 1
    on = np.linalg.norm(s.emitter_positions[point[:, 0] == 1] - s.emitter_positions.mean(0))
    assert on <= np.linalg.norm(s.emitter_positions - s.emitter_positions.mean(0), axis=1).min() + 1e-12
    binary = named_pattern("binary", s)
    assert set(np.unique(binary)) == {0.0, 1.0} and 0.4 < binary.mean() < 0.6
    np.testing.assert_array_equal(binary, named_pattern("binary", s))  # fixed, not random per call
