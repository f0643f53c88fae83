"""``ntp bench scan``: the whole pipeline (virtual scan -> SfM -> traces -> network -> fit) on
virtual scans of the demo asset at several sizes (photos x texture resolution), with per-stage
time and the errors against ground truth side by side; the number of photos is the knob the paper
studies (Figs. 15-16). Writes a table, JSON and a matplotlib plot of run time against error."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from ..io.progress import QUIET
from ..sim import demo
from . import dump_json, print_table

SIZES = [(24, 128), (48, 256), (96, 256)]  # (photos, map resolution); 0.25 camera scale


def run(
    sizes: list[tuple[int, int]] | None = None,
    json_path: Path | None = None,
    plot: Path | None = None,
    work: Path | None = None,
    known_poses: bool = False,
) -> dict:
    """The demo pipeline at each (photos, resolution) in ``sizes``: stage times and errors, a table, JSON, a plot."""
    sizes = sizes or SIZES
    rows, results = [], []
    with tempfile.TemporaryDirectory(prefix="ntp-bench-scan-") as tmp:
        for views, res in sizes:
            out = (work or Path(tmp)) / f"v{views}_r{res}"
            s = demo.run(
                out, views=views, resolution=res, known_poses=known_poses, progress=QUIET, blend=False, refine=False
            )
            st = s["seconds"]["stages"]
            r = {
                "photos": views,
                "resolution": res,
                **s["metrics"],
                "pose_error": s["pose_error"],
                "seconds_virtual_scan": s["seconds"]["virtual_scan"],
                "seconds_reconstruct": s["seconds"]["reconstruct"],
                "stages": st,
            }
            results.append(r)
            pe = s["pose_error"].get("centre_median_m", float("nan")) * 1e3
            rows.append(
                (
                    views,
                    f"{res}^2",
                    f"{st['register']:.1f}",
                    f"{st['traces']:.1f}",
                    f"{st['network_and_fit']:.1f}",
                    f"{s['seconds']['reconstruct']:.1f}",
                    f"{pe:.2f}",
                    f"{r['normal_median_deg']:.2f}",
                    f"{r['diffuse_rmse']:.4f}",
                    f"{r['relit_ssim']:.4f}",
                    f"{r['coverage']:.3f}",
                )
            )
    print_table(
        rows,
        (
            "photos",
            "maps",
            "SfM s",
            "traces s",
            "net+fit s",
            "reconstruct s",
            "pose mm",
            "normal deg",
            "diffuse RMSE",
            "relit SSIM",
            "coverage",
        ),
    )
    if plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
        t = [r["seconds_reconstruct"] for r in results]
        for a, key, label in zip(
            ax,
            ("normal_median_deg", "diffuse_rmse", "relit_ssim"),
            ("normal median error (deg)", "diffuse albedo RMSE", "relit SSIM (higher is better)"),
        ):
            a.plot(t, [r[key] for r in results], "o-")
            for r, x in zip(results, t):
                a.annotate(
                    f"{r['photos']} photos, {r['resolution']}²",
                    (x, r[key]),
                    fontsize=8,
                    textcoords="offset points",
                    xytext=(4, 4),
                )
            a.set_xlabel("reconstruct wall time (s, 2 CPU cores)")
            a.set_ylabel(label)
            a.grid(alpha=0.3)
        fig.suptitle("ntp bench scan: run time against error (virtual scans of the demo asset)")
        fig.tight_layout()
        plot.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(plot, dpi=110)
        print(f"wrote {plot}")
    data = {"sizes": results}
    dump_json(json_path, data)
    return data


def sizes(text: str) -> list[tuple[int, int]]:
    """``--sizes``: ``PHOTOSxRES,...`` as (photos, resolution) pairs."""
    try:
        return [(int(a), int(b)) for a, b in (item.lower().split("x") for item in text.split(","))]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected PHOTOSxRES,...") from None


HELP = "whole pipeline on virtual scans of 2-3 sizes: stage times vs errors"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench scan``'s options."""
    parser.add_argument("--sizes", type=sizes, default=None, help="PHOTOSxRES,... (default 24x128,48x256,96x256)")
    parser.add_argument("--known-poses", action="store_true", help="skip SfM (true poses)")
    parser.add_argument("--plot", type=Path, default=Path("bench_scan.png"), help="PNG of run time against error")
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench scan``: the benchmark with the command line's options; the exit code."""
    run(args.sizes, json_path=args.json, plot=args.plot, known_poses=args.known_poses)
    return 0
