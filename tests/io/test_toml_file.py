import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.toml_file import check_keys, read_toml, unknown_key


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
    with pytest.raises(NtpInputError, match=r"is a folder, not a file"):
        read_toml(tmp_path, "missing")


def test_unknown_keys_are_refused_with_the_nearest_known_one(tmp_path):
    known = ("mesh", "photos", "poses")
    check_keys({"mesh": 1, "photos": 2}, known, tmp_path / "s.toml")
    with pytest.raises(NtpInputError, match=r"s.toml: key 'pose': unknown key \(did you mean 'poses'\?\)"):
        check_keys({"mesh": 1, "pose": 2}, known, tmp_path / "s.toml")
    assert unknown_key("zzz", known) == "unknown key (known keys: mesh, photos, poses)"


def test_non_utf8_text_is_named(tmp_path):
    bad = tmp_path / "device.toml"
    bad.write_bytes(b'name = "caf\xe9"\n')
    with pytest.raises(NtpInputError, match=r"device.toml: not UTF-8 text \(byte 0xe9 at offset 11\)"):
        read_toml(bad, "missing")
