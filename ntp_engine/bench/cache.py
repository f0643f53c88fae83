"""``ntp bench cache``: what content-keyed caching costs. Hashing a scan's photos (full-size 8-bit
PNGs with sensor noise, so they compress like real photos) with the pipeline's ``content_key``
(SHA-256, threads) against one thread and against the stat() key it replaced (name, size, mtime:
free, but blind to copies and edits); projected to the paper's 1000-photo scans. Then the checksum
check of a cache entry on reuse, projected to a 1000-photo x 1024^2 trace table (~7.75 GB).
Files are read from the page cache (just written): a cold disk adds its read time to both keys'
first use.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ..io.images import write_png
from ..io.stage_cache import content_key, file_digest
from ..scanner.device_file import load_scanner
from . import dump_json, print_table

TRACE_TABLE_GB_1000_PHOTOS = 7.75  # 1000 photos x 1024^2 texels (docs/performance: ~323 entries/texel)


def _photo(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth lit-object-like image plus 2-code sensor noise, in [0, 1]."""
    y, x = np.mgrid[0:height, 0:width] / max(width, height)
    base = 0.4 + 0.3 * np.sin(6 * x)[..., None] * np.cos(4 * y)[..., None] * np.array([1.0, 0.8, 0.6])
    return np.clip(base + rng.normal(0, 2 / 255, (height, width, 3)), 0, 1)


def run(photos: int = 40, scale: float = 1.0, big_mb: int = 512, json_path=None) -> dict:
    """Seconds to key ``photos`` photos at ``scale`` of the default camera three ways, and the
    checksum rate on a ``big_mb`` MB file; printed and returned."""
    cam = load_scanner()
    w, h = int(round(cam.width * scale)), int(round(cam.height * scale))
    root = Path(tempfile.mkdtemp(prefix="ntp-bench-cache-"))
    try:
        rng = np.random.default_rng(0)
        write_png(root / "0000.png", _photo(w, h, rng))
        data = (root / "0000.png").read_bytes()
        paths = [root / f"{i:04d}.png" for i in range(photos)]
        for i, p in enumerate(paths[1:], 1):
            p.write_bytes(data + i.to_bytes(4, "little"))  # distinct files of a photo's size
        mb = sum(p.stat().st_size for p in paths) / 1e6

        t0 = time.perf_counter()
        for p in paths:
            st = p.stat()
            _ = (p.name, st.st_size, st.st_mtime_ns)
        t_stat = time.perf_counter() - t0
        t0 = time.perf_counter()
        for p in paths:
            file_digest(p)
        t_one = time.perf_counter() - t0
        t0 = time.perf_counter()
        content_key(paths)
        t_key = time.perf_counter() - t0

        big = root / "traces.npz"
        chunk = rng.integers(0, 255, 1 << 20, dtype=np.uint8).tobytes()
        with open(big, "wb") as fh:
            for _ in range(big_mb):
                fh.write(chunk)
        t0 = time.perf_counter()
        file_digest(big)
        t_big = time.perf_counter() - t0
    finally:
        shutil.rmtree(root, ignore_errors=True)

    per = {"stat (old key)": t_stat, "sha256, 1 thread": t_one, "sha256, threads (content_key)": t_key}
    rows = [
        (name, f"{t:.3f}", f"{t / photos * 1e3:.2f}", f"{t / photos * 1000:.1f}", f"{t / t_key:.2f}")
        for name, t in per.items()
    ]
    print(f"{photos} photos of {w}x{h}, {mb / photos:.1f} MB each (page cache)")
    print_table(rows, ("key", "s", "ms / photo", "s / 1000 photos", "x content_key"))
    rate = big_mb / 1e3 / t_big
    print(
        f"cache checksum check: {rate:.2f} GB/s -> {TRACE_TABLE_GB_1000_PHOTOS / rate:.1f} s for a "
        f"{TRACE_TABLE_GB_1000_PHOTOS} GB trace table (1000 photos x 1024^2)"
    )
    result = {
        "photos": photos,
        "photo_size": [w, h],
        "mb_per_photo": mb / photos,
        "seconds": per,
        "seconds_per_1000_photos": {k: t / photos * 1000 for k, t in per.items()},
        "checksum_gb_per_s": rate,
        "seconds_check_trace_table_1000_photos": TRACE_TABLE_GB_1000_PHOTOS / rate,
    }
    dump_json(json_path, result)
    return result


HELP = "content keys: hashing photos (vs one thread, vs stat) and cache checksums"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench cache``'s options."""
    parser.add_argument("--photos", type=int, default=40, help="photos hashed (projected to 1000)")
    parser.add_argument("--scale", type=float, default=1.0, help="photo size (1.0 = 2448x2048)")
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench cache``: the benchmark with the command line's options; the exit code."""
    run(photos=args.photos, scale=args.scale, json_path=args.json)
    return 0
