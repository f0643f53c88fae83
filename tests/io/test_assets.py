from ntp_engine.io.assets import ASSETS, DEMO_DIR, DEVICES_DIR, MODELS_DIR


def test_shipped_assets_are_found():
    assert (DEVICES_DIR / "ntp_led_32x16.toml").is_file() and (MODELS_DIR / "compact" / "model.pt").is_file()
    assert (DEMO_DIR / "mesh.obj").is_file() and DEMO_DIR.parent == ASSETS
