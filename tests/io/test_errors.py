from pathlib import Path

from ntp_engine.io.errors import NtpInputError


def test_message_is_one_line_naming_the_file():
    err = NtpInputError(Path("scan") / "scan.toml", "key 'mesh'\n  missing\tentirely")
    assert str(err) == "scan/scan.toml: key 'mesh' missing entirely" and err.path == Path("scan/scan.toml")
    assert str(NtpInputError(None, "need --views >= 3")) == "need --views >= 3"
    assert isinstance(err, ValueError)
