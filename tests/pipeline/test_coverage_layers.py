import numpy as np

from ntp_engine.pipeline.coverage_layers import LAYERS, RAMP, ramp_colours


def test_ramp_colours_run_from_bad_red_to_good_green_clamped():
    photos = LAYERS["photos"]  # 0 photos bad, 16+ good
    c = ramp_colours(np.array([-3.0, 0.0, 8.0, 16.0, 99.0, np.nan]), photos)
    red, yellow, green = (np.array(col[:3]) for _, col in RAMP)
    assert np.allclose(c, [red, red, yellow, green, green, red])
    normal = LAYERS["normal"]  # reversed: 10 deg bad, 0 good
    assert np.allclose(ramp_colours(np.array([0.0, 10.0]), normal), [green, red])


def test_every_layer_names_a_result_file_and_a_channel():
    for layer in LAYERS.values():
        assert layer.file.endswith(".exr") and 0 <= layer.channel <= 3 and layer.bad != layer.good
