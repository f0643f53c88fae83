"""The refinement's settings: the noise model's floor and growth, and defaults that are usable
(positive rounds and iterations, the noise's robust scale beyond one sigma)."""

import dataclasses

import pytest
import torch

from ntp_engine.refine.settings import TUNING, RefineSettings, SensorNoise


def test_the_noise_has_a_floor_for_dark_pixels_and_grows_with_the_signal():
    noise = SensorNoise(read_code=1.0, relative=0.03)
    y = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    s = noise.sigma(y)
    assert abs(s[0].item() - 1 / 255) < 1e-12
    assert abs(s[2].item() ** 2 - ((1 / 255) ** 2 + 0.03**2)) < 1e-12
    assert s[0] < s[1] < s[2]


def test_the_defaults_are_usable_and_the_settings_are_frozen():
    st = RefineSettings()
    assert st.rounds > 0 and st.iterations > 0 and st.noise.robust > 1
    assert TUNING.model.noise_scale[0] <= 1.0 <= TUNING.model.noise_scale[1]
    with pytest.raises(dataclasses.FrozenInstanceError):
        st.rounds = 1  # type: ignore[misc]
