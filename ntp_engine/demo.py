"""``ntp demo``: what the engine can show today on the default device.

Prints the default device, then writes for one sample surface point (an anisotropic, glossy,
orange material at the centre of the valid volume) its diffuse and specular lumitexels (as
unfolded cube crosses) and its per-LED measurement (one pixel per LED, laid out as the panel).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from .atomic import write_text_atomic
from .device import Device
from .images import write_png
from .lumitexel import DIFFUSE_RES, SPECULAR_RES, render_lumitexels, unfold_cross
from .measurement import confidence, measure, physical_lumitexel

SAMPLE = {
    "rho_d": [0.45, 0.2, 0.05],
    "rho_s": [2.0, 2.0, 2.0],
    "alpha_x": 0.25,
    "alpha_y": 0.04,
    "tilt_deg": 15.0,  # shading normal tilted from the lumitexel z towards +x
    "tangent_deg": 30.0,  # tangent rotated about the normal
}


def _sample_frame(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    a, b = math.radians(SAMPLE["tilt_deg"]), math.radians(SAMPLE["tangent_deg"])
    n = torch.tensor([math.sin(a), 0.0, math.cos(a)], dtype=dtype)
    t0 = torch.tensor([math.cos(a), 0.0, -math.sin(a)], dtype=dtype)
    b0 = torch.linalg.cross(n, t0, dim=-1)
    return n, math.cos(b) * t0 + math.sin(b) * b0


def _upscale(img: np.ndarray, k: int) -> np.ndarray:
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1)


def run(out: Path, device_path: Path | None = None) -> dict:
    device = Device.load(device_path)
    print(device.summary())
    out.mkdir(parents=True, exist_ok=True)
    f64 = dict(dtype=torch.float64)
    n, t = _sample_frame()
    rho_d, rho_s = torch.tensor(SAMPLE["rho_d"], **f64), torch.tensor(SAMPLE["rho_s"], **f64)
    ax, ay = torch.tensor(SAMPLE["alpha_x"], **f64), torch.tensor(SAMPLE["alpha_y"], **f64)

    diffuse, specular = render_lumitexels(n, t, rho_d, rho_s, ax, ay)
    d_img = unfold_cross(diffuse, DIFFUSE_RES).numpy()
    s_img = unfold_cross(torch.log1p(specular), SPECULAR_RES).numpy()
    write_png(out / "lumitexel_diffuse.png", _upscale((d_img / d_img.max()) ** (1 / 2.2), 16))
    write_png(out / "lumitexel_specular.png", _upscale((s_img / s_img.max()) ** (1 / 2.2), 4))

    # the sample point at the valid-volume centre, its normal facing halfway between camera and panel
    x = torch.tensor(device.valid_center, **f64)
    panel_dir = torch.tensor(device.emitter_positions.mean(0), **f64) - x
    n_cam = torch.nn.functional.normalize(torch.nn.functional.normalize(-x, dim=0)
                                          + torch.nn.functional.normalize(panel_dir, dim=0), dim=0)
    t_cam = torch.nn.functional.normalize(torch.linalg.cross(n_cam, torch.tensor([0.0, 1.0, 0.0], **f64), dim=0), dim=0)
    m = physical_lumitexel(device, x, n_cam, t_cam, rho_d, rho_s, ax, ay)  # (L, 3)
    p_eff = device.effective_pattern(torch.as_tensor(device.pattern, **f64))
    per_led = (m * p_eff).numpy()
    b = measure(device, m)
    pixel = device.encode(device.exposure(device.pattern) * b)
    beta = confidence(device, x[None], n_cam[None], t_cam[None], ax, ay, rho_s.mean())
    if device.grid_shape:
        cols, rows = device.grid_shape
        led_img = per_led.reshape(rows, cols, 3)
    else:
        led_img = per_led.reshape(1, -1, 3)
    write_png(out / "measurement_per_led.png", _upscale(led_img / max(led_img.max(), 1e-12), 16))

    result = {
        "device": device.name,
        "sample_brdf": SAMPLE,
        "point_camera_space_m": x.tolist(),
        "normal_camera_space": n_cam.tolist(),
        "measurement_B": b.tolist(),
        "pixel_code_value": pixel.tolist(),
        "highlight_confidence_beta": float(beta),
        "files": ["lumitexel_diffuse.png", "lumitexel_specular.png", "measurement_per_led.png"],
    }
    write_text_atomic(out / "demo.json", json.dumps(result, indent=2))
    print(f"sample point B = {np.round(b.numpy(), 3).tolist()} -> 8-bit {np.round(pixel.numpy(), 1).tolist()}, "
          f"beta = {float(beta):.3f}")
    print(f"wrote {out}/lumitexel_diffuse.png, lumitexel_specular.png, measurement_per_led.png, demo.json")
    return result
