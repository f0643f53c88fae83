"""The add-on registers and unregisters cleanly in the real bpy, twice, and its panel draws."""
import bpy

import ntp_addon


def test_register_unregister_twice():
    for _ in range(2):
        ntp_addon.register()
        assert hasattr(bpy.types, "NTP_PT_device")
        assert "ntp_device_path" in bpy.types.Scene.bl_rna.properties
        bpy.context.scene.ntp_device_path = ""
        ntp_addon.unregister()
        assert not hasattr(bpy.types, "NTP_PT_device")
        assert "ntp_device_path" not in bpy.types.Scene.bl_rna.properties


def test_panel_lines_name_the_device_or_the_error(tmp_path):
    from ntp_addon.panel import _device_lines

    assert _device_lines("")[0].startswith("device   ntp-led-32x16")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = 1\n")
    (line,) = _device_lines(str(bad))
    assert line.startswith("error: ") and "bad.toml" in line and "name" in line
