"""When a registration is refused: the photos do not confirm it (its cost is not sharp enough) or a
rival azimuth fits them nearly as well (``refusal``); what a symmetry of the mesh means for it
(``symmetry_note``: placements a symmetry relates give the same asset, so they are accepted, said,
never rivals); and the picture that shows a user the mesh's outline over a few photos
(``outline_picture``).
"""

from __future__ import annotations

import numpy as np

from ..io.mesh import Mesh
from ..io.raycast import RayCaster
from ..scanner import camera
from .check import PhotoCheck, confirmed_by_outline, min_margin, outline_fits, spread_within_bar
from .photo_stack import PhotoStack, edge_mask
from .settings import TUNING


def named_rival(candidates: list[dict]) -> int | None:
    """The candidate an ambiguity names: the best-fitting one (coarse cost) more than
    ``TUNING.align.ambiguous_deg`` from the chosen and not a symmetry of the mesh (``equivalent``);
    None when there is none."""
    rivals = [
        i
        for i, c in enumerate(candidates)
        if abs(c["azimuth_change_deg"]) > TUNING.align.ambiguous_deg and not c.get("equivalent", False)
    ]
    return min(rivals, key=lambda i: candidates[i]["coarse_cost"]) if rivals else None


def refusal_kind(check: PhotoCheck) -> str | None:
    """Which test refuses a registration — ``unconfirmed`` or ``ambiguous``, in that order — or None
    when the photos confirm it. A symmetry of the mesh refuses nothing: the placements it relates put
    every surface point where the photos see one (no cost can choose) and give the same asset."""
    if check.outline is not None:
        return None if confirmed_by_outline(check) else ("unconfirmed" if not outline_fits(check) else "ambiguous")
    if check.cloud is None and (
        check.fit.points < TUNING.photometric.min_views or check.sharpness < TUNING.refusal.min_sharpness
    ):
        return "unconfirmed"
    if check.cloud is not None and not spread_within_bar(check):
        return "unconfirmed"
    if check.margin < min_margin(check):
        return "ambiguous"
    return None


def symmetry_note(check: PhotoCheck) -> str | None:
    """What the mesh's symmetry about the vertical means for the registration (one line), or None
    when it has none: e.g. "symmetric under a 180 deg turn: one of 2 equivalent placements"."""
    turns = check.equivalent_turns
    if turns is None:
        return "a body of revolution: every turn about the vertical is an equivalent placement (the same asset)"
    if not turns:
        return None
    named = ", ".join(f"{abs(t) if abs(abs(t) - 180.0) < 0.5 else t:.0f}" for t in turns)
    return f"symmetric under a {named} deg turn: one of {len(turns) + 1} equivalent placements (the same asset)"


def refusal(check: PhotoCheck) -> str | None:
    """Why the photos do not confirm a registration (one line, ``refusal_kind``'s cause), or None
    when they do."""
    kind = refusal_kind(check)
    if kind == "unconfirmed" and check.cloud is not None:
        spread = check.cloud["spread_px"]
        said = "cannot be measured" if spread is None else f"is {spread:.2f} px at the object (1 sigma)"
        return (
            f"the points triangulated on the object do not fix where the mesh is: the placement's spread {said}, "
            f"a confirmed one <= {TUNING.triangulation.max_spread_px:g} px; a nearly round shape or a noisy mesh, "
            "or too few photos: take more (full-size) photos or give a poses file"
        )
    if kind == "unconfirmed" and check.outline is not None:
        o = check.outline
        return (
            f"the object's outline against the board does not fix where the mesh is: {100 * o['points_outside']:.1f}% "
            f"of its points lie over print a photo sees (at most {100 * TUNING.silhouette.max_outside:g}%), its spread "
            f"is {o['spread_px']:.2f} px (at most {TUNING.silhouette.max_spread_px:g}): a mesh that is not the "
            "object's, or too few photos seeing the board around it: take more photos or give a poses file"
        )
    if kind == "unconfirmed":
        return (
            f"the photos cannot confirm where the mesh is (moved {TUNING.photometric.sharpness_shift_px:g} px it "
            f"fits them {100 * max(check.sharpness, 0.0):.0f}% worse, a confirmed registration "
            f">= {100 * TUNING.refusal.min_sharpness:.0f}%): "
            "the mesh is not where the photos show it, or the object is too plain to tell"
        )
    if kind == "ambiguous":
        i = named_rival(check.candidates)
        assert i is not None  # a finite margin has a rival
        rival = check.candidates[i]
        if check.outline is not None:
            fits = (
                f"its outline against the board nearly as well (worse by {check.margin:.2f} standard errors "
                f"over photos < {min_margin(check):g}"
            )
        elif check.cloud is not None:
            fits = (
                f"the points triangulated on the object nearly as well (worse by {check.margin:.2f} standard errors "
                f"between surface regions < {min_margin(check):g}"
            )
        else:
            fits = f"the photos nearly as well (margin {check.margin:.2f} < {min_margin(check)}"
        return (
            f"the object's azimuth is ambiguous: turned by {rival['azimuth_change_deg']:.0f} deg it fits {fits}; "
            f"the mesh turned so lies {rival['mesh_turned_mm']:.1f} mm from itself)"
        )
    return None


OUTLINE = np.array([1.0, 0.1, 0.9])  # magenta: rare in photos


def outline_picture(photos: PhotoStack, poses: np.ndarray, mesh: Mesh, count: int = 4) -> np.ndarray:
    """``count`` photos (evenly spread) with the mesh's silhouette and depth edges drawn over them
    under ``poses (V, 4, 4)``, tiled 2 wide: sRGB-ish display values ``(H, W, 3)`` in [0, 1]."""
    s = photos.scanner
    caster = RayCaster([mesh.triangles])
    rays = camera.pixel_rays(s).reshape(-1, 3)
    picks = np.linspace(0, len(poses) - 1, min(count, len(poses))).round().astype(int)
    tiles = []
    for j in picks:
        R, t = poses[j][:3, :3], poses[j][:3, 3]
        hits = caster.intersect(np.broadcast_to(-R.T @ t, rays.shape), rays @ R)
        edge = edge_mask((hits.geom >= 0).reshape(s.height, s.width), hits.t.reshape(s.height, s.width))
        img = photos.linear[j].permute(1, 2, 0).numpy().clip(0, 1) ** (1 / 2.2)
        img[edge] = OUTLINE
        tiles.append(img)
    while len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + 2], 1) for i in range(0, len(tiles), 2)]
    return np.concatenate(rows, 0)
