import json
import struct

import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.glb import read_glb


def _glb(doc: dict, binary: bytes = b"") -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def test_a_glb_is_read_back_as_its_json_and_binary_chunk(tmp_path):
    path = tmp_path / "a.glb"
    path.write_bytes(_glb({"asset": {"version": "2.0"}}, b"\1\2\3\4"))
    doc, binary = read_glb(path)
    assert doc == {"asset": {"version": "2.0"}} and binary == b"\1\2\3\4"
    path.write_bytes(b"PK\3\4 not a glb at all")
    with pytest.raises(NtpInputError, match="a.glb: not a binary glTF"):
        read_glb(path)
    path.write_bytes(b"glTF" + struct.pack("<IIII", 2, 24, 4, 0x004E4942) + b"\0\0\0\0")  # a binary chunk alone
    with pytest.raises(NtpInputError, match="no JSON chunk"):
        read_glb(path)
