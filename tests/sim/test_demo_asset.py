"""The virtual scanner: renders agree with the physics core; scans are complete and reproducible."""

import numpy as np

from ntp_engine.io.maps import SVBRDFMaps


def test_demo_asset_exercises_the_whole_model():
    maps = SVBRDFMaps.load("assets/demo/ground_truth")
    ax, ay = maps.roughness[..., 0], maps.roughness[..., 1]
    spec, diff = maps.specular_albedo.mean(-1), maps.diffuse_albedo.mean(-1)
    assert ax.min() <= 0.0101 and (ax / ay).max() > 10  # roughness down to 0.01; strong anisotropy
    assert ((spec < 0.1) & (diff > 0.3)).mean() > 0.2  # diffuse-dominant region
    assert ((ax == ay) & (spec > 1)).mean() > 0.2  # glossy isotropic region
    aniso = ax > 5 * ay
    t = maps.tangent[aniso]
    assert np.ptp(np.arctan2(t[:, 1], t[:, 0])) > 2.0  # the tangent direction varies
    assert maps.diffuse_albedo.min() >= 0.25
    np.testing.assert_allclose(np.linalg.norm(maps.normal, axis=-1), 1, atol=1e-5)
    assert np.abs((maps.normal * maps.tangent).sum(-1)).max() < 1e-5
