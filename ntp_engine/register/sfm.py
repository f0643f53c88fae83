"""Structure from motion (pycolmap): the photos' camera poses and a sparse cloud in an arbitrary frame.

SIFT features, sequential matching (a hand-held sweep: each photo against its neighbours, with
quadratic overlap), mapping with the device's intrinsics held fixed (OPENCV model; COLMAP puts pixel
centres at +0.5, the device file at integers). The largest model wins; photos it does not contain
are reported as unregistered.

Mappers (``MAPPERS``): ``incremental`` (COLMAP's), ``global`` (GLOMAP: rotation averaging and global
positioning, then one bundle adjustment) and ``hierarchical`` (the sweep cut into overlapping
clusters mapped incrementally, then merged). ``auto`` (the default) picks by photo count, as ``ntp
bench sfm`` measured them: incremental below ``TUNING.sfm.global_from_photos``, global from there (at 300
photos as fast and more accurate, at 1000 twice as fast and more accurate; on tens of photos it
is the least reliable).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.errors import NtpInputError
from ..io.progress import QUIET, Progress
from ..io.threads import colmap_threads
from ..scanner.scanner import Scanner
from .settings import TUNING

MAPPERS = ("incremental", "global", "hierarchical")


def chosen_mapper(mapper: str, photos: int) -> str:
    """The mapper ``mapper`` (one of ``MAPPERS`` or ``auto``) names for ``photos`` photos."""
    if mapper == "auto":
        return "global" if photos >= TUNING.sfm.global_from_photos else "incremental"
    if mapper not in MAPPERS:
        raise ValueError(f"unknown mapper {mapper!r} (have auto, {', '.join(MAPPERS)})")
    return mapper


@dataclass
class SfmResult:
    """A structure-from-motion model: poses by photo name, sparse points, photos left out."""

    poses: dict[str, np.ndarray]  # photo name -> 4x4 camera-from-world (SfM frame)
    points: np.ndarray  # (P, 3) sparse points, SfM frame
    unregistered: list[str]
    model: Path | None = None  # the chosen model's COLMAP folder (under ``work``), if written


def structure_from_motion(
    photos_dir: Path,
    names: list[str],
    scanner: Scanner,
    work: Path,
    overlap: int = 10,
    progress: Progress = QUIET,
    peak_threshold: float = 0.0067,
    seed: int | None = None,
    mapper: str = "auto",
) -> SfmResult:
    """SfM poses of ``names`` (camera-from-world in SfM's frame) with the scanner's intrinsics held
    fixed; ``work`` is emptied and holds COLMAP's database. ``peak_threshold`` is SIFT's (lowering it
    adds backdrop points, not object points, on virtual scans). ``seed`` seeds COLMAP's random choices;
    ``mapper`` is one of ``MAPPERS`` or ``auto`` (by the number of photos, ``chosen_mapper``)."""
    import pycolmap

    mapper = chosen_mapper(mapper, len(names))

    pycolmap.logging.minloglevel = 2  # COLMAP logs every image at INFO; errors still surface
    if seed is not None:  # RANSAC and mapping choices (threads still vary the result slightly)
        pycolmap.set_random_seed(seed)
    bar = progress.counter("SfM (features, matching, mapping)", 3, "stage")
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    db = work / "database.db"
    K, d = scanner.K, scanner.distortion
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    reader.camera_params = ",".join(str(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, *d[:4]))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.peak_threshold = peak_threshold
    extraction.num_threads = colmap_threads()
    pycolmap.extract_features(
        db,
        photos_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
    )
    bar.update()
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = overlap
    pairing.quadratic_overlap = True
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = colmap_threads()
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing)
    bar.update()
    models = _map(pycolmap, mapper, db, photos_dir, work / "sparse", seed)
    bar.update()
    bar.close()
    if not models:
        raise NtpInputError(
            photos_dir, "structure-from-motion found no initial image pair (too few features or overlap between photos)"
        )
    index, rec = max(models.items(), key=lambda kv: kv[1].num_reg_images())
    model_dir = work / "sparse" / str(index)
    poses = {}
    for image in rec.images.values():
        m = np.eye(4)
        m[:3, :4] = image.cam_from_world().matrix()
        poses[image.name] = m
    if len(poses) < TUNING.sfm.min_registered:
        raise NtpInputError(photos_dir, f"only {len(poses)} photos registered (need {TUNING.sfm.min_registered})")
    points = np.array([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() else np.zeros((0, 3))
    return SfmResult(poses, points, sorted(set(names) - set(poses)), model_dir if model_dir.is_dir() else None)


def _map(pycolmap, mapper: str, db: Path, photos_dir: Path, out: Path, seed: int | None) -> dict:
    """COLMAP's ``mapper`` on the matched database, intrinsics held fixed; models by index. The
    mappers' own options carry the seed (pycolmap's global one does not reach GLOMAP's choices)."""
    out.mkdir(parents=True, exist_ok=True)
    incremental = pycolmap.IncrementalPipelineOptions()
    incremental.num_threads = colmap_threads()
    if seed is not None:
        incremental.random_seed = seed
    incremental.ba_refine_focal_length = False
    incremental.ba_refine_principal_point = False
    incremental.ba_refine_extra_params = False
    if mapper == "incremental":
        return pycolmap.incremental_mapping(db, photos_dir, out, incremental)
    if mapper == "hierarchical":
        hierarchical = pycolmap.HierarchicalPipelineOptions()
        hierarchical.incremental_options = incremental
        hierarchical.num_threads = colmap_threads()
        return pycolmap.hierarchical_mapping(db, photos_dir, out, hierarchical)
    glomap = pycolmap.GlobalPipelineOptions()
    glomap.num_threads = colmap_threads()
    if seed is not None:
        glomap.random_seed = glomap.mapper.random_seed = seed
    ba = glomap.mapper.bundle_adjustment
    ba.refine_focal_length = ba.refine_principal_point = ba.refine_extra_params = False
    return pycolmap.global_mapping(db, photos_dir, out, glomap)
