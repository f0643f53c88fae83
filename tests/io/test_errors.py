import pickle
from pathlib import Path

from ntp_engine.io.errors import NtpInputError


def test_message_is_one_line_naming_the_file():
    err = NtpInputError(Path("scan") / "scan.toml", "key 'mesh'\n  missing\tentirely")
    assert str(err) == "scan/scan.toml: key 'mesh' missing entirely" and err.path == Path("scan/scan.toml")
    assert str(NtpInputError(None, "need --views >= 3")) == "need --views >= 3"
    assert isinstance(err, ValueError)


def test_error_line_names_the_file_of_an_os_error():
    import errno

    from ntp_engine.io.errors import error_line

    assert error_line(OSError(errno.ENOSPC, "No space left on device", "out/x.exr")) == (
        "out/x.exr: No space left on device"
    )
    assert error_line(OSError(errno.EIO, "I/O\nerror")) == "[Errno 5] I/O error"
    assert error_line(NtpInputError("a.toml", "bad")) == "a.toml: bad"


def test_pickles_as_itself():
    """A worker's error (Ray, multiprocessing) comes back with its file and problem."""
    err = pickle.loads(pickle.dumps(NtpInputError("scan/scan.toml", "key 'mesh' missing")))
    assert isinstance(err, NtpInputError) and str(err) == "scan/scan.toml: key 'mesh' missing"
    assert pickle.loads(pickle.dumps(NtpInputError(None, "no path"))).path is None
