import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.toml_file import read_toml


def test_reads_tables_and_names_the_file_on_every_failure(tmp_path):
    good = tmp_path / "a.toml"
    good.write_text('mesh = "m.obj"\n[camera]\nwidth = 3\n')
    assert read_toml(good, "missing") == {"mesh": "m.obj", "camera": {"width": 3}}
    with pytest.raises(NtpInputError, match=r"b.toml: no scan here"):
        read_toml(tmp_path / "b.toml", "no scan here")
    bad = tmp_path / "c.toml"
    bad.write_text("mesh = \n")
    with pytest.raises(NtpInputError, match=r"c.toml: not valid TOML"):
        read_toml(bad, "missing")
    with pytest.raises(NtpInputError, match=r"cannot read"):
        read_toml(tmp_path, "missing")  # a folder


def test_non_utf8_text_is_named(tmp_path):
    bad = tmp_path / "device.toml"
    bad.write_bytes(b'name = "caf\xe9"\n')
    with pytest.raises(NtpInputError, match=r"device.toml: not UTF-8 text \(byte 0xe9 at offset 11\)"):
        read_toml(bad, "missing")
