import os
import re
import socket

import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.input_file import regular_file


def test_a_regular_file_within_its_bound_is_accepted_and_a_link_to_one_followed(tmp_path):
    f = tmp_path / "a.toml"
    f.write_text("x = 1\n")
    (tmp_path / "link.toml").symlink_to(f)
    assert regular_file(f, 100) == 6 and regular_file(tmp_path / "link.toml", 100) == 6


def test_anything_else_is_named_without_being_opened(tmp_path):
    os.mkfifo(tmp_path / "fifo.png")  # open() would block forever
    (tmp_path / "zero.png").symlink_to("/dev/zero")  # read() would never end
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(tmp_path / "s"))
    cases = {
        "fifo.png": "is a FIFO (named pipe), not a file",
        "zero.png": "is a character device, not a file",
        "s": "is a socket, not a file",
        ".": "is a folder, not a file",
        "none.png": "does not exist",
    }
    for name, message in cases.items():
        with pytest.raises(NtpInputError, match=re.escape(message)) as err:
            regular_file(tmp_path / name)
        assert str(err.value).startswith(str(tmp_path))
    sock.close()


def test_a_file_over_its_kinds_bound_is_refused_unread(tmp_path):
    f = tmp_path / "huge.json"
    with open(f, "wb") as fh:
        fh.truncate(3 << 20)  # sparse: nothing is written or read
    with pytest.raises(NtpInputError, match=r"huge.json: is 3 MB; a file of this kind is at most 2 MB"):
        regular_file(f, 2 << 20)
    assert regular_file(f, 3 << 20) == 3 << 20
