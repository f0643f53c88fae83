"""Tuned values carry their provenance; a field without one, or a measurement without its objects, is refused."""

from dataclasses import dataclass, field

import numpy as np
import pytest

from ntp_engine.io.tuned import Kind, budget, derived, measured, provenance, unmeasured


@dataclass(frozen=True)
class _Inner:
    scale: float = derived(1.4826, "the MAD of a Gaussian: 1.4826 sigma")
    grid: np.ndarray = budget(np.arange(3.0), "three steps: the search's cost")


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)
    rounds: int = measured(4, "3 -> 4 moved the knot's tangents 9 -> 6 deg", on="the knot: ntp bench gallery")
    floor: float = unmeasured(0.3, "a choice")


def test_provenance_lists_every_field_with_its_kind_reason_and_source_nested_sections_by_dotted_name():
    rows = {r.name: r for r in provenance(_Outer)}
    assert list(rows) == ["inner.scale", "inner.grid", "rounds", "floor"]
    assert [r.kind for r in rows.values()] == [Kind.DERIVED, Kind.BUDGET, Kind.MEASURED, Kind.UNMEASURED]
    assert rows["rounds"].on == "the knot: ntp bench gallery" and rows["inner.scale"].on == ""
    assert rows["inner.scale"].value == "1.4826" and rows["inner.grid"].value == "[0., 1., 2.]"


def test_an_array_default_is_each_instances_own():
    a, b = _Inner(), _Inner()
    assert a.grid is not b.grid and np.array_equal(a.grid, b.grid)


def test_a_value_without_a_reason_or_a_measurement_without_its_objects_is_refused():
    with pytest.raises(ValueError, match="reason"):
        derived(1.0, " ")
    with pytest.raises(ValueError, match="measured on"):
        measured(1.0, "it was better", on="")


def test_a_field_declared_without_provenance_is_refused():
    @dataclass(frozen=True)
    class Bare:
        ok: float = budget(1.0, "cheap")
        bare: float = 2.0

    with pytest.raises(TypeError, match="Bare.bare"):
        provenance(Bare)
