"""The pipeline stages' tuned constants (``PipelineTuning``, one section per stage: photo selection,
trace assembly, the network + fit stage, the run's refusal of too little data), every value declared
with its provenance (``io.tuned``; the table of them all is ``docs/tuning.md``, generated from here).

The refinement's and the registration's own are in ``refine.settings`` and ``register.settings``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..io.tuned import budget, derived, measured, unmeasured


@dataclass(frozen=True)
class SelectTuning:
    """Photo selection (``pipeline.photo_selection``)."""

    blur_margin: float = unmeasured(
        0.08,
        "a photo whose blur (Crete et al., 0 sharp .. 1 blurred) exceeds the scan's median by more is dropped; "
        "a 1-pixel Gaussian blur adds ~0.14 on virtual scans, so it drops a blur of about half a pixel or more",
    )


@dataclass(frozen=True)
class TraceTuning:
    """Trace assembly (``pipeline.traces``)."""

    min_cos_grazing: float = measured(
        0.2,
        "wo . n^ in (this, physics.shadows.MIN_COS_VIEW]: kept, flagged out of range, read by the refinement only "
        "for texels with no other entry; 0.2 rather than 0.15 halves what the gained texels cost the knot's albedo",
        on='the knot (docs/history/accuracy.md, "Grazing entries"): ntp bench gallery --poses true --refine',
    )
    max_tap_tilt_deg: float = measured(
        20.0,
        "a bilinear tap whose ray hits the mesh this far (chord angle) off the entry's tangent plane sees another "
        "surface; one smooth surface tilts a few degrees across a pixel. At 20 and 30 nearly the same of the knot's "
        "grazing entries have a tap off their surface (7,832 and 7,818)",
        on='the knot (docs/history/accuracy.md, "Pixels that see another surface"): ntp bench gallery --refine',
    )
    tap_tolerance: float = derived(1e-6, "metres off the plane always accepted: the hit's float32 rounding")
    sky_rays: int = budget(
        64, "directions over a texel's hemisphere: none hitting the mesh = it cannot shadow its emitters"
    )
    table_block_entries: int = budget(
        1 << 23, "entries per block when a table on disk is regrouped by texel: ~400 MB of rows in memory"
    )


@dataclass(frozen=True)
class FitTuning:
    """The network + fit stage (``pipeline.fit_traces``)."""

    network_views: int = measured(
        64,
        "entries per trace the network reads, spread evenly over the trace: the length it was trained on; its "
        "validation loss is lowest there (2.08 at 64 views vs 2.15 at 128); a 1000-photo scan's traces cost 5x less",
        on="the network's validation set (docs/network.md): ntp train",
    )
    albedo_views: int = unmeasured(
        16, "entries per texel for the beta check and the albedo least squares (Eq. 1 per entry and emitter)"
    )
    rho_s_prior_weight: float = measured(
        1.0,
        "the network's rho_s counts as this many views in the albedo least squares: demo diffuse RMSE 0.0432 -> "
        "0.0417, relit SSIM 0.887 -> 0.892 (0.25: 0.0427, 0.889)",
        on="the demo only (docs/pipeline.md): ntp demo",
    )
    fit_block: int = budget(
        4096, "texels per unit of work (a Ray task with --ray): a few seconds and ~10 MB of traces at 60 photos"
    )


@dataclass(frozen=True)
class DistilTuning:
    """The scan's own network (``pipeline.distil``): the shipped network fine-tuned on a sample of the
    scan's texels refined against their photos, then run over every texel (``--distil``)."""

    seeds: int = budget(
        2048,
        "texels refined against their photos as the teacher (~7-13 s of refinement on 2 cores at 256^2); other "
        "counts not compared at the same rate and steps (4096 was tried only with another learning rate)",
    )
    held_out: float = derived(
        0.2, "share of the seeds kept out of the fine-tuning to decide when it stops (early stopping)"
    )
    batch: int = unmeasured(64, "traces per fine-tuning step: the network's training batch (docs/network.md)")
    learning_rate: float = measured(
        3e-4,
        "Adam's rate; 1e-4 left the held-out loss at 0.23 after 400 steps where 3e-4 reached 0.19 "
        "(and the teacher's tangents within 3.5 deg, not 5.7)",
        on="the demo (tuning), true poses, 256^2 (docs/distillation.md)",
    )
    max_steps: int = budget(
        800,
        "fine-tuning steps at most: ~0.04 s each on 2 cores (batch 64, the compact network, fused Adam: 32.8 s for "
        "800 steps inside a 256^2 demo run; per-op Adam took 0.065-0.07 s there, its sqrt slow on zero moments)",
    )
    check_every: int = budget(50, "steps between evaluations of the held-out loss")
    patience: int = derived(
        3, "evaluations without a lower held-out loss before the fine-tuning stops (the best weights kept)"
    )
    polish_rounds: int = budget(1, "rounds of the refinement of every texel from the distilled answer")
    polish_iterations: int = measured(
        2,
        "LM iterations of that round, no multi-start: relit SSIM 0.942 / 0.963 / 0.976 at 0 / 1 / 2 (the full "
        "refinement 0.988; from the shipped network's answer 2 gave 0.945, tangents 11.9 deg against 0.48)",
        on="the demo (tuning), true poses, 256^2 (docs/distillation.md)",
    )


@dataclass(frozen=True)
class RunTuning:
    """What a run must have measured to be a result (``pipeline.stages``): below, refused (exit 2)."""

    min_photos_used: int = unmeasured(3, "photos that see the mesh at least")
    min_coverage: float = unmeasured(
        0.05, "texels with a trace at least: below, the mesh and the poses are likely not in one frame"
    )


@dataclass(frozen=True)
class PipelineTuning:
    """The pipeline stages' tuned constants, one section per stage (fixed per release; ``docs/tuning.md``)."""

    select: SelectTuning = field(default_factory=SelectTuning)
    traces: TraceTuning = field(default_factory=TraceTuning)
    fit: FitTuning = field(default_factory=FitTuning)
    distil: DistilTuning = field(default_factory=DistilTuning)
    run: RunTuning = field(default_factory=RunTuning)


TUNING = PipelineTuning()

# the reconstruction paths: network + fit alone, the scan's own network (``reconstruct(distil=True)``,
# ``--distil``), every texel refined (``reconstruct(refine=True)``, ``--refine``)
PATHS = ("fast", "distil", "refine")
