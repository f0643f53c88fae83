"""Surface points triangulated from photos whose poses are known (a marker board's): SIFT features
(OpenCV) matched between photos that view the object from nearby directions, each match
triangulated from its two rays and kept where both photos see it within
``TUNING.triangulation.max_reprojection_px`` from a baseline of at least
``TUNING.triangulation.min_parallax_deg``.

Convention: poses are camera-from-frame 4x4 (OpenCV axes, metres); the points come back in that
frame. Pixels at integer centres, as the device file: OpenCV's SIFT is run with its precise
upscaling, without which its keypoints sit a fraction of a pixel off that convention.

A highlight moves with the scanner's light, so a feature on one matches nothing fixed on the
surface: such matches rarely survive both reprojection tests, and those that do lie off the mesh,
where the alignment's trimmed distances leave them out (``align.align_on_board``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..scanner.scanner import Scanner
from .settings import TUNING


@dataclass
class Features:
    """One photo's SIFT features: undistorted normalised image coordinates ``(F, 2)`` (x / z, y / z
    in the camera) and descriptors ``(F, 128)`` float32."""

    rays: np.ndarray
    descriptors: np.ndarray


def photo_features(codes: np.ndarray, scanner: Scanner) -> Features:
    """SIFT features of a photo of 8-bit codes ``(H, W, 3)`` (at most
    ``TUNING.triangulation.features_per_photo``, the strongest), found on the photo averaged down by
    the smallest whole factor that brings it within ``TUNING.triangulation.max_feature_width``; the
    rays are the full photo's (a pixel k of the smaller image is the full one's f (k + 0.5) - 0.5)."""
    import cv2

    gray = cv2.cvtColor(np.clip(codes, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    factor = -(-gray.shape[1] // TUNING.triangulation.max_feature_width)
    if factor > 1:
        h, w = gray.shape[0] // factor, gray.shape[1] // factor
        gray = cv2.resize(gray[: h * factor, : w * factor], (w, h), interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT.create(
        nfeatures=TUNING.triangulation.features_per_photo,
        contrastThreshold=TUNING.triangulation.contrast_threshold,
        enable_precise_upscale=True,
    )
    everywhere = np.full(gray.shape, 255, np.uint8)  # the stubs take no None for "no mask"
    keypoints, descriptors = sift.detectAndCompute(gray, everywhere)
    if descriptors is None or not keypoints:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    pixels = factor * (np.array([k.pt for k in keypoints], np.float64).reshape(-1, 1, 2) + 0.5) - 0.5
    rays = cv2.undistortPoints(pixels, scanner.K, scanner.distortion).reshape(-1, 2)
    return Features(rays, np.asarray(descriptors, np.float32))


def photo_pairs(poses: list[np.ndarray], aim: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of the photos ``poses`` to match: each photo with its
    ``TUNING.triangulation.neighbours`` nearest others by the angle between their directions to the
    object's centre ``aim (3,)``, within ``TUNING.triangulation.max_pair_deg`` (further apart, SIFT's
    descriptors no longer match the same surface)."""
    centres = np.array([-p[:3, :3].T @ p[:3, 3] for p in poses])
    to = centres - aim
    to /= np.linalg.norm(to, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(to @ to.T, -1.0, 1.0)))
    np.fill_diagonal(angle, np.inf)
    pairs = set()
    for i in range(len(poses)):
        for j in np.argsort(angle[i])[: TUNING.triangulation.neighbours]:
            if angle[i, j] <= TUNING.triangulation.max_pair_deg:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _matches(a: Features, b: Features) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``a`` and ``b`` of the features matched by Lowe's ratio test
    (``TUNING.triangulation.ratio``), each feature of ``b`` used once."""
    import cv2

    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < TUNING.triangulation.ratio * m[1].distance]
    ia = np.array([m.queryIdx for m in good], int)
    ib = np.array([m.trainIdx for m in good], int)
    _, first = np.unique(ib, return_index=True)
    return ia[first], ib[first]


def triangulate_pair(
    pose_a: np.ndarray, pose_b: np.ndarray, rays_a: np.ndarray, rays_b: np.ndarray, fx: float
) -> np.ndarray:
    """The points ``(M, 3)`` (the poses' frame) of matched normalised coordinates ``rays_a, rays_b
    (M, 2)`` (linear triangulation), those that pass the reprojection (``fx`` converts to pixels),
    parallax and in-front tests only."""
    import cv2

    if not len(rays_a):
        return np.zeros((0, 3))
    h = cv2.triangulatePoints(pose_a[:3], pose_b[:3], rays_a.T.astype(np.float64), rays_b.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (h[:3] / h[3]).T
    ok = np.isfinite(x).all(1)
    for pose, rays in ((pose_a, rays_a), (pose_b, rays_b)):
        cam = x @ pose[:3, :3].T + pose[:3, 3]
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            err = fx * np.linalg.norm(cam[:, :2] / depth[:, None] - rays, axis=1)
        ok &= (depth > 0) & (err < TUNING.triangulation.max_reprojection_px)
    ca, cb = (-p[:3, :3].T @ p[:3, 3] for p in (pose_a, pose_b))
    ra, rb = x - ca, x - cb
    cos = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-30)
    ok &= cos < np.cos(np.radians(TUNING.triangulation.min_parallax_deg))
    return x[ok]


def triangulated_points(
    features: list[Features], poses: list[np.ndarray], scanner: Scanner, aim: np.ndarray
) -> np.ndarray:
    """Points ``(P, 3)`` in the poses' frame triangulated from the photos' ``features`` (one per pose
    in ``poses``) over the pairs ``photo_pairs`` chooses around ``aim``, each kept where a point of
    another pair lies within ``TUNING.triangulation.max_reprojection_px`` (at the object's distance):
    a surface point is found again by other pairs of photos that see it; a reflection in a glossy
    surface, or a highlight, moves with the viewpoint and is not."""
    found, pair = [np.zeros((0, 3))], [np.zeros(0, int)]
    for k, (i, j) in enumerate(photo_pairs(poses, aim)):
        ia, ib = _matches(features[i], features[j])
        x = triangulate_pair(poses[i], poses[j], features[i].rays[ia], features[j].rays[ib], scanner.fx)
        found.append(x)
        pair.append(np.full(len(x), k))
    points, pairs = np.concatenate(found), np.concatenate(pair)
    if len(points) < 2:
        return points
    centres = np.array([-p[:3, :3].T @ p[:3, 3] for p in poses])
    reach = (
        TUNING.triangulation.max_reprojection_px * float(np.median(np.linalg.norm(centres - aim, axis=1))) / scanner.fx
    )
    tree = cKDTree(points)
    close = tree.query_pairs(reach, output_type="ndarray")
    other = close[pairs[close[:, 0]] != pairs[close[:, 1]]]
    again = np.zeros(len(points), bool)
    again[other.ravel()] = True
    return points[again]
