"""The add-on's scripts are started as this Python's ``-m`` modules, and only the named ones."""

import sys

import pytest

from ntp_engine.io.blender_process import BLENDER_SCRIPTS, blender_command, has_bpy


def test_a_script_runs_in_this_python_as_a_module_with_its_arguments():
    assert blender_command("batch", "R", "--blend", "a.blend") == [
        sys.executable,
        "-m",
        BLENDER_SCRIPTS["batch"],
        "R",
        "--blend",
        "a.blend",
    ]
    assert isinstance(has_bpy(), bool)


def test_an_unknown_script_is_refused():
    with pytest.raises(ValueError, match="no Blender script 'render'"):
        blender_command("render")
