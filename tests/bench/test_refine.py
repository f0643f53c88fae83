"""``ntp bench refine``'s machinery on one tiny gallery scan (not its accuracy): a row per material
and variant, speeds, the scipy baseline, the files."""

import json

from ntp_engine.bench import gallery
from ntp_engine.bench import refine as bench_refine

TINY = gallery.GallerySettings(objects=("box",), scanners=("engine",), views=6, scale=0.06, resolution=16)


def test_tiny_refine_bench(tmp_path):
    bench = bench_refine.RefineBench(
        gallery=TINY, objects=("box",), scanners=("engine",), per_material=6, baseline_texels=1
    )
    r = bench_refine.run(tmp_path, bench)
    variants = ["network + fit"] + [label for label, _ in bench_refine.VARIANTS]
    materials = {row["material"] for row in r["rows"]}
    assert materials <= {"lacquer_mirror", "metal_brushed_line", "matte_white", "metal_rough"} and materials
    for m in materials:
        assert [row["variant"] for row in r["rows"] if row["material"] == m] == variants
    assert all(s["texels_per_s"] > 0 for s in r["speed"]) and len(r["speed"]) == len(bench_refine.VARIANTS)
    base = r["baseline"][0]
    assert base["texels"] == 1 and base["speed_ratio"] > 0 and "normal_deg" in base["scipy"]
    md = (tmp_path / "refine.md").read_text()
    assert md.count("| box | engine |") >= len(materials) * len(variants)
    assert json.loads((tmp_path / "refine.json").read_text())["bench"]["per_material"] == 6


def test_tune_and_validate_side_by_side_per_variant_and_kind():
    rows = [
        {"variant": "refined", "kind": "lacquer", "set": "tune", "normal_deg": 1.0},
        {"variant": "refined", "kind": "lacquer", "set": "tune", "normal_deg": 2.0},
        {"variant": "refined", "kind": "lacquer", "set": "validate", "normal_deg": 4.5},
        {"variant": "refined", "kind": "matte", "set": "validate", "normal_deg": float("nan")},
    ]
    lines = bench_refine._set_lines(rows, ("normal_deg",))
    assert lines[2] == "| refined | lacquer | 2 / 1 | 1.5 / 4.5 (+3) |"
    assert lines[3] == "| refined | matte | 0 / 1 | - / - |"
