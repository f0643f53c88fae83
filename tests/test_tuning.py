"""docs/tuning.md is generated from the settings dataclasses' declared provenance and is up to date,
and the refinement's and the registration's tuned values have one home: their settings modules."""

import ast
from pathlib import Path

import tuning_table

from ntp_engine.io.tuned import Kind, provenance

ENGINE = Path(__file__).resolve().parent.parent / "ntp_engine"
# module-level constants of refine/ and register/ that are facts, not tuned values
FACTS = {
    "CENSOR_CODE", "ANISOTROPY_PARAMS", "LOBE_PARAMS", "TANGENT_PARAMS", "N_PARAMS", "N_DERIVATIVES",
    "PACKED_ROWS", "SAMPLE_ARRAYS", "LOWER", "UPPER", "REFINE_FLAGS", "MODEL_FILES", "MAPPERS", "WORK",
    "OUTLINE", "P_OMEGA", "P_LOGA", "P_RHO_D", "P_RHO_S", "PROGRESS_STAGES",
    "GALLERY", "ENGINE_GALLERY", "CYCLES_GALLERY", "REGISTRATION_BENCH", "TUNING",
}  # fmt: skip


def test_the_tuning_table_is_up_to_date():
    assert tuning_table.DOC.read_text(encoding="utf-8") == tuning_table.table(), (
        "docs/tuning.md is out of date: run `python tools/tuning_table.py`"
    )


def test_every_tuned_value_declares_its_provenance_and_every_measurement_names_what_it_was_measured_on():
    for _, _, cls, _ in tuning_table.SETTINGS:
        rows = provenance(cls)  # raises for a field declared without one
        assert rows and all(r.why for r in rows)
        assert all(r.on for r in rows if r.kind is Kind.MEASURED)


def test_the_refinement_and_registration_modules_hold_no_tuned_constant_outside_their_settings():
    strays = []
    for package in ("refine", "register"):
        for path in sorted((ENGINE / package).glob("*.py")):
            for node in ast.parse(path.read_text(encoding="utf-8")).body:
                targets = node.targets if isinstance(node, ast.Assign) else []
                for t in targets:
                    for name in [t] if isinstance(t, ast.Name) else getattr(t, "elts", []):
                        if (
                            isinstance(name, ast.Name)
                            and name.id.isupper()
                            and not name.id.startswith("_")
                            and name.id not in FACTS
                        ):
                            strays.append(f"{package}/{path.name}: {name.id}")
    assert not strays, f"tuned values belong in refine/settings.py or register/settings.py: {strays}"
