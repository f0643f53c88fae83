"""Write docs/tuning.md: every tunable constant of the refinement and the registration, its value,
and where the value comes from, read from the comments beside and above it in the code (the one
home of each constant and of its reason). ``python tools/tuning_table.py`` rewrites the file;
``tests/test_tuning.py`` fails when it is out of date.

A constant's provenance is classified from its comment: **measured** (it cites a measurement: a
before/after, a bench, a gallery object or a docs section), **derived** (it cites a rule: a
statistic, a quantisation, a geometric or numerical argument), **budget** (it trades run time or
memory, not accuracy), or **unexplained** (none of these: to be justified by a measurement on the
validation set, or removed).
"""

from __future__ import annotations

import ast
import io
import re
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MODULES = [
    "ntp_engine/refine/settings.py",
    "ntp_engine/refine/inputs.py",
    "ntp_engine/refine/passes.py",
    "ntp_engine/refine/policy.py",
    "ntp_engine/refine/material_pass.py",
    "ntp_engine/refine/materials.py",
    "ntp_engine/refine/footprint.py",
    "ntp_engine/refine/support_light.py",
    "ntp_engine/register/photo_stack.py",
    "ntp_engine/register/photometric.py",
    "ntp_engine/register/check.py",
    "ntp_engine/register/refusal.py",
    "ntp_engine/register/align.py",
]
DOC = ROOT / "docs" / "tuning.md"
# what a comment must cite to count as each kind (checked in this order)
MEASURED = re.compile(
    r"(measured|->|→|gallery|docs/|bench|dome|vase|blob|box|knot|demo|cycles|engine scan|lost|cost the|"
    r"\d+(\.\d+)? (vs|against) \d|\d+: [-+]?\d+%|[-+]\d+(\.\d+)?%|"
    r"at \d+(\.\d+)?[,:]? [^ ]+ (was|were|gave|made|moved))",
    re.I,
)
DERIVED = re.compile(
    r"(bic|aic|chi|sigma|quantis|nyquist|1\.4826|mad|by construction|half a|float32|float64|rounding|"
    r"degrees of freedom|parameters?:|adds to|what a|the paper|paper's|spacing|pitch|range|bound|limit|definition|"
    r"per pixel|pixel|code|8-bit|bits|radians|unit)",
    re.I,
)
BUDGET = re.compile(r"(mb|gb|memory|seconds|per batch|batch|speed|faster|slower|time|cost|cheap|~\d)", re.I)
NOT_TUNABLE = {"_NAMES", "_BROAD_COLOUR", "SAMPLE_ARRAYS", "WORK", "OUTLINE", "REFINE_FLAGS"}


def _comments(source: str) -> dict[int, str]:
    """Comment text by line number."""
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = tok.string.lstrip("#").strip()
    return out


def constants(path: Path) -> list[dict]:
    """The module-level UPPER_CASE constants of ``path`` and the numeric fields of its settings
    dataclasses (classes named ``*Settings`` or ``*Noise``, as ``Class.field``): name, value as
    written, reason, kind."""
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    notes = _comments(source)
    rows: list[dict] = []

    def scan(body: list[ast.stmt], prefix: str, start_after: int) -> None:
        prev_end = start_after
        for node in body:
            start, end = node.lineno, node.end_lineno or node.lineno
            targets: list[ast.expr] = []
            if isinstance(node, ast.Assign):
                targets = node.targets
            elif isinstance(node, ast.AnnAssign):
                targets = [node.target]
            elif isinstance(node, ast.ClassDef) and not prefix and node.name.endswith(("Settings", "Noise")):
                scan(node.body, node.name + ".", node.lineno)
            flat = [e for t in targets for e in ([t] if isinstance(t, ast.Name) else getattr(t, "elts", []))]
            names = [
                prefix + e.id
                for e in flat
                if isinstance(e, ast.Name)
                and (e.id.isupper() or prefix)
                and e.id not in NOT_TUNABLE
                and not e.id.startswith("_")
            ]
            value_node = getattr(node, "value", None)
            numeric = value_node is not None and not (
                prefix and isinstance(value_node, ast.Call)  # a field(default_factory=...) holds another record
            )
            if names and numeric:
                above = []
                k = start - 1
                while k > prev_end and k in notes and lines[k - 1].lstrip().startswith("#"):
                    above.insert(0, notes[k])
                    k -= 1
                beside = [notes[i] for i in range(start, end + 1) if i in notes]
                reason = " ".join(above + beside).strip()
                value = " ".join((ast.get_source_segment(source, value_node) or "").split())
                rows.append({"names": names, "value": value, "reason": reason, "kind": kind(reason)})
            prev_end = end

    scan(ast.parse(source).body, "", 0)
    return rows


def kind(reason: str) -> str:
    """measured / derived / budget / unexplained, from a constant's comment."""
    if not reason:
        return "unexplained"
    if MEASURED.search(reason):
        return "measured"
    if DERIVED.search(reason):
        return "derived"
    if BUDGET.search(reason):
        return "budget"
    return "unexplained"


def table() -> str:
    """docs/tuning.md's text."""
    out = [
        "# Tuning: every constant and where its value comes from",
        "",
        "Generated by `python tools/tuning_table.py` from the code (do not edit; `tests/test_tuning.py`",
        "fails when it is out of date). Each row is a module-level constant of the refinement or the",
        "registration or a field of their settings dataclasses, its value as written, and its reason as",
        "its comment states it. **Kind**: *measured*",
        "(the comment cites a measurement — a before/after, a bench, a gallery object, a docs section),",
        "*derived* (a rule: a statistic, the camera's quantisation, a geometric or numerical argument),",
        "*budget* (run time or memory, not accuracy), *unexplained* (no stated reason: to be justified",
        "by a measurement on the validation set, or removed). Every measurement so far was on the five",
        'gallery objects at 40 photos — the tuning set (docs/accuracy.md, "The rule for changes").',
        "",
    ]
    counts: dict[str, int] = {}
    for rel in MODULES:
        rows = constants(ROOT / rel)
        if not rows:
            continue
        out += [f"## `{rel}`", "", "| constant | value | kind | reason (the code's comment) |", "|---|---|---|---|"]
        for r in rows:
            counts[r["kind"]] = counts.get(r["kind"], 0) + len(r["names"])
            reason = r["reason"].replace("|", "\\|") or "–"
            value = r["value"].replace("|", "\\|")
            out.append(f"| `{', '.join(r['names'])}` | `{value}` | {r['kind']} | {reason} |")
        out.append("")
    total = sum(counts.values())
    summary = ", ".join(f"{counts.get(k, 0)} {k}" for k in ("measured", "derived", "budget", "unexplained"))
    at = next(i for i, line in enumerate(out) if line.startswith("## "))
    out[at:at] = [f"**{total} constants: {summary}.**", ""]
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    text = table()
    if "--check" in sys.argv:
        sys.exit(0 if DOC.read_text(encoding="utf-8") == text else 1)
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC.relative_to(ROOT)}")
