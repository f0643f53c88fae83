"""The per-texel answer the fit stage hands on (``pipeline.fit_traces``), and the refinement after
it (``refine.passes.refine_fit``): one typed record of arrays instead of string-keyed ones, saved
to and loaded from the stage caches' ``.npz`` files.

Convention: N texels (trace i = texel i of the atlas), every vector in the texel's geometric frame
(n^, t^ as the lumitexel's z and x): ``n_loc, t_loc (N, 3)``, ``alpha (N, 2)`` = (alpha_x along
t_loc, alpha_y), ``flags (N,)`` ``fit.flags.TexelFlag`` bits, ``rho_d, rho_s (N, 3)`` linear RGB.
Texels no trace reached keep the defaults (+z, +x, ``FALLBACK_ALPHA``, zeros).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .geometry import FALLBACK_ALPHA

# the basis materials' table keys in a saved fit (``refine.materials.BasisMaterials.to_arrays``)
MATERIAL_PREFIX = "material_"
_MATTE_SHARE, _WIDTH_VARIES = "material_matte_share", "material_width_varies"


@dataclass
class TexelFit:
    """Per-texel parameters (module docstring); the refinement's extras are None without it."""

    n_loc: np.ndarray  # (N, 3)
    t_loc: np.ndarray  # (N, 3)
    alpha: np.ndarray  # (N, 2)
    flags: np.ndarray  # (N,) TexelFlag bits
    rho_d: np.ndarray  # (N, 3)
    rho_s: np.ndarray  # (N, 3)
    std: np.ndarray | None = None  # (N, 4) 1-sigma of normal (deg), tangent (deg), log alpha, log rho_s
    highlight: np.ndarray | None = None  # (N,) the lobe's largest share of an entry's pixel
    noise_scale: float | None = None  # the noise model's calibration factor
    normal_prior_at_mesh: bool | None = None  # where the normal's weak pull centred
    material: np.ndarray | None = None  # (N,) basis material; -1 matte, -2 unobserved
    materials: dict[str, np.ndarray] | None = None  # the basis materials' table (``MATERIAL_PREFIX`` keys)
    matte_share: float | None = None  # the matte class's share estimated on this object
    width_varies: np.ndarray | None = None  # (K,) materials whose lobe width is a field over the object

    @classmethod
    def defaults(cls, n: int) -> TexelFit:
        """``n`` texels no trace reached."""
        n_loc, t_loc = np.zeros((n, 3)), np.zeros((n, 3))
        n_loc[:, 2], t_loc[:, 0] = 1.0, 1.0
        zeros = np.zeros((n, 3))
        return cls(n_loc, t_loc, np.full((n, 2), FALLBACK_ALPHA), np.zeros(n, np.int64), zeros, zeros.copy())

    def __len__(self) -> int:
        return len(self.flags)

    def copy(self) -> TexelFit:
        """A copy whose arrays are the record's own."""
        return TexelFit.from_arrays({k: v.copy() for k, v in self.arrays().items()})

    def arrays(self) -> dict[str, np.ndarray]:
        """Flat named arrays (``from_arrays`` reads them back; an ``.npz``'s layout)."""
        out: dict[str, np.ndarray] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None or f.name in ("materials", "matte_share", "width_varies"):
                continue
            out[f.name] = np.asarray(v)
        if self.materials is not None:
            out.update(self.materials)
        if self.matte_share is not None:
            out[_MATTE_SHARE] = np.asarray(self.matte_share)
        if self.width_varies is not None:
            out[_WIDTH_VARIES] = np.asarray(self.width_varies)
        return out

    @classmethod
    def from_arrays(cls, z: Mapping[str, np.ndarray]) -> TexelFit:
        """The record ``arrays`` wrote."""

        def opt(key: str) -> np.ndarray | None:
            return np.asarray(z[key]) if key in z else None

        table = {
            k: np.asarray(z[k]) for k in z if k.startswith(MATERIAL_PREFIX) and k not in (_MATTE_SHARE, _WIDTH_VARIES)
        }
        noise, at_mesh, matte = opt("noise_scale"), opt("normal_prior_at_mesh"), opt(_MATTE_SHARE)
        return cls(
            np.asarray(z["n_loc"]),
            np.asarray(z["t_loc"]),
            np.asarray(z["alpha"]),
            np.asarray(z["flags"]),
            np.asarray(z["rho_d"]),
            np.asarray(z["rho_s"]),
            std=opt("std"),
            highlight=opt("highlight"),
            noise_scale=None if noise is None else float(noise),
            normal_prior_at_mesh=None if at_mesh is None else bool(at_mesh),
            material=opt("material"),
            materials=table or None,
            matte_share=None if matte is None else float(matte),
            width_varies=opt(_WIDTH_VARIES),
        )

    def save(self, path: Path) -> None:
        """Write the record to ``path`` (``.npz``)."""
        np.savez(path, **self.arrays())

    @classmethod
    def load(cls, path: Path) -> TexelFit:
        """The record ``save`` wrote to ``path``."""
        with np.load(path) as z:
            return cls.from_arrays({k: z[k] for k in z.files})
