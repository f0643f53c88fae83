"""The result's coverage layers: which channel of which result file shows how well the photos
measured each point, its display range and legend (bpy-free; the add-on's overlay and the result
page draw them through the same ramp).

Convention: a layer maps its value from ``bad`` (0, red) to ``good`` (1, green), clamped; the
ranges are display scales (16 photos, 10° / 30°, a factor e), not accuracy claims.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .result import UNCERTAINTY_FILE

RAMP = ((0.0, (0.85, 0.05, 0.03, 1.0)), (0.5, (0.95, 0.8, 0.05, 1.0)), (1.0, (0.05, 0.7, 0.1, 1.0)))  # bad → good


@dataclass(frozen=True)
class Layer:
    """One overlay: ``file``'s ``channel`` (0-3 = RGBA) shown from ``bad`` (red) to ``good``
    (green), clamped; ``legend`` names both ends; ``hint`` says what to do about red."""

    label: str
    file: str
    channel: int
    bad: float
    good: float
    legend: tuple[str, str]
    hint: str


LAYERS: dict[str, Layer] = {
    "highlight": Layer(
        "Highlight seen",
        "confidence.exr",
        0,
        0.0,
        1.0,
        ("no lobe fitted", "lobe fitted"),
        "red: no photo caught its highlight — sweep the light across it at other angles",
    ),
    "photos": Layer(
        "Photos per point",
        "confidence.exr",
        1,
        0.0,
        16.0,
        ("0 photos", "16+ photos"),
        "red: few photos saw it — scan that side again",
    ),
    "normal": Layer(
        "Normal uncertainty",
        UNCERTAINTY_FILE,
        0,
        10.0,
        0.0,
        ("10°+", "0°"),
        "1-sigma of the normal given its photos (refined results)",
    ),
    "tangent": Layer(
        "Tangent uncertainty",
        UNCERTAINTY_FILE,
        1,
        30.0,
        0.0,
        ("30°+", "0°"),
        "1-sigma of the anisotropy direction (refined results; red on isotropic points is expected)",
    ),
    "roughness": Layer(
        "Roughness uncertainty",
        UNCERTAINTY_FILE,
        2,
        1.0,
        0.0,
        ("×2.7+", "exact"),
        "1-sigma of log roughness (refined results)",
    ),
    "specular": Layer(
        "Specular uncertainty",
        UNCERTAINTY_FILE,
        3,
        1.0,
        0.0,
        ("×2.7+", "exact"),
        "1-sigma of log specular albedo (refined results)",
    ),
}


def ramp_colours(values: np.ndarray, layer: Layer) -> np.ndarray:
    """``values (...)`` of ``layer`` as display colours ``(..., 3)`` in [0, 1] through ``RAMP``
    (linear between its stops, as Blender's colour ramp interpolates); NaN counts as bad."""
    span = layer.good - layer.bad
    s = np.clip(np.nan_to_num((np.asarray(values, np.float64) - layer.bad) / span, nan=0.0), 0.0, 1.0)
    stops = np.array([p for p, _ in RAMP])
    colours = np.array([c[:3] for _, c in RAMP])
    return np.stack([np.interp(s, stops, colours[:, k]) for k in range(3)], -1)
