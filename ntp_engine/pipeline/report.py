"""A run's report (``report.json``): typed sections, filled as the stages finish, written as JSON.

The file's layout is the contract (docs/pipeline.md, "The report"): ``to_json`` writes it with the
sections in this order and leaves out a section no stage filled (``refine`` without the
refinement; ``traces``, ``texels`` and ``model`` in a registration alone).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class PhotoCounts:
    """The scan's photos: how many, which the selection dropped, how many the traces used."""

    total: int
    kept: int
    blurry: dict[str, float]  # name -> blur score
    unreadable: list[str]
    used: int | None = None  # photos that see a texel (the traces stage); None before it


@dataclass
class TraceCounts:
    """What assembling traces kept (texel-view pairs) and why it rejected the rest."""

    entries: int  # in range: what the network and the fitter read
    table_entries: int  # in range or not: the table's rows
    views_used: int
    views_seeing_no_texel: int
    rejected: dict[str, int]


@dataclass
class TexelCounts:
    """The atlas's texels: how many, how many some photo saw, how many carry a flag."""

    total: int
    observed: int
    coverage: float  # observed / total (0 for an empty atlas)
    flagged: int
    resolution: int
    # share of the observed texels more anisotropic than Cycles' Principled BSDF draws (10:1;
    # io.viewers): there the .blend's accurate material, not the Principled one, shows the measurement
    beyond_cycles_principled: float | None = None
    # share of the observed texels whose glTF base colour rho_d / (1 - 0.04 rho_s) passes 1 and is
    # clipped (io.viewers.base_colour_for_fresnel_mix): there a glTF viewer's diffuse is darker than measured
    gltf_base_colour_clipped: float | None = None


@dataclass
class RefineSummary:
    """The refinement's noise calibration and the basis materials' reach (None: not computed)."""

    noise_scale: float | None = None
    normal_prior: str | None = None  # "mesh" or "start": where the normal's weak pull centred
    basis_materials: int | None = None
    matte_share: float | None = None
    texels_lobe_from_material: int | None = None
    texels_width_from_material: int | None = None
    materials_width_varies: int | None = None


@dataclass
class Report:
    """One run's report; ``stages`` holds each stage's wall seconds in the order they finished."""

    scan: str | None = None
    stages: dict[str, float] = field(default_factory=dict)
    photos: PhotoCounts | None = None
    registration: dict[str, Any] | None = None  # the registration's diagnostics (docs/pipeline.md)
    traces: TraceCounts | None = None
    refine: RefineSummary | None = None
    distil: dict[str, Any] | None = None  # the scan's own network (pipeline.distil.DistilReport, seconds_fit)
    texels: TexelCounts | None = None
    model: dict[str, Any] | None = None  # the network's name and its training summary
    cached_stages: list[str] | None = None
    recomputed_damaged_stages: list[str] | None = None
    seconds: float | None = None

    def timed(self, stage: str, t0: float) -> None:
        """Record ``stage``'s wall seconds since ``t0`` (``time.perf_counter``)."""
        self.stages[stage] = round(time.perf_counter() - t0, 3)

    def to_json(self) -> dict[str, Any]:
        """``report.json``'s content: the filled sections, None fields left out."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                value = {k: v for k, v in dataclasses.asdict(value).items() if v is not None}
            out[f.name] = value
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Report:
        """A report read back from ``report.json`` (``to_json``'s inverse)."""
        sections = {"photos": PhotoCounts, "traces": TraceCounts, "texels": TexelCounts, "refine": RefineSummary}
        kwargs = {k: (sections[k](**v) if k in sections else v) for k, v in data.items()}
        return cls(**kwargs)
