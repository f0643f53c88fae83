"""Tuned values with their provenance: the field helpers a stage's settings dataclass declares its
constants with, and the rows ``docs/tuning.md`` is generated from.

Every tunable value states where it comes from, in one of four kinds:

- **measured**: chosen by a measurement; ``on`` names the objects and the command that measured it;
- **derived**: follows from a rule (a statistic, the camera's quantisation, a geometric or
  numerical argument) stated in ``why``;
- **budget**: trades run time or memory, not accuracy (``why`` says what it costs);
- **unmeasured**: a modelling choice no measurement backs yet; the list the validation set is for.

Convention: the helpers return ``dataclasses.field`` objects (typed ``Any`` so that a field reads
``x: float = derived(0.5, "...")``); an unhashable default (a numpy array) is copied per instance.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np


class Kind(StrEnum):
    """Where a tuned value comes from."""

    MEASURED = "measured"
    DERIVED = "derived"
    BUDGET = "budget"
    UNMEASURED = "unmeasured"


def _field(default: Any, kind: Kind, why: str, on: str = "") -> Any:
    if not why.strip():
        raise ValueError("a tuned value needs its reason")
    metadata = {"kind": kind, "why": why.strip(), "on": on.strip()}
    if isinstance(default, np.ndarray):
        return dataclasses.field(default_factory=default.copy, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def measured(default: Any, why: str, *, on: str) -> Any:
    """A value chosen by a measurement: ``on`` names the objects and the command."""
    if not on.strip():
        raise ValueError("a measured value names what it was measured on")
    return _field(default, Kind.MEASURED, why, on)


def derived(default: Any, why: str) -> Any:
    """A value that follows from the rule ``why`` states."""
    return _field(default, Kind.DERIVED, why)


def budget(default: Any, why: str) -> Any:
    """A value that trades run time or memory, not accuracy."""
    return _field(default, Kind.BUDGET, why)


def unmeasured(default: Any, why: str) -> Any:
    """A modelling choice no measurement backs yet (to be measured on the validation set)."""
    return _field(default, Kind.UNMEASURED, why)


@dataclass(frozen=True)
class Provenance:
    """One tuned value: its field name, value as a string, kind and reason."""

    name: str
    value: str
    kind: Kind
    why: str
    on: str


def provenance(settings: Any) -> list[Provenance]:
    """The tuned fields of the settings dataclass (class or instance) ``settings``, in declaration
    order; a field that holds another settings dataclass contributes its own as ``outer.inner``.
    Raises ``TypeError`` for a field declared without a provenance."""
    instance = settings() if isinstance(settings, type) else settings
    rows: list[Provenance] = []
    for f in dataclasses.fields(instance):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value) and not f.metadata:
            rows += [dataclasses.replace(r, name=f"{f.name}.{r.name}") for r in provenance(value)]
            continue
        if "kind" not in f.metadata:
            raise TypeError(f"{type(instance).__name__}.{f.name} is declared without its provenance")
        text = np.array2string(value, separator=", ") if isinstance(value, np.ndarray) else repr(value)
        rows.append(Provenance(f.name, text, f.metadata["kind"], f.metadata["why"], f.metadata["on"]))
    return rows


def retuned(settings: Any, section: str, **values: Any) -> Any:
    """``settings`` (a frozen settings dataclass) with ``values`` replaced in its field ``section``
    (itself a settings dataclass): one experiment's changed constants, the rest as released."""
    return dataclasses.replace(settings, **{section: dataclasses.replace(getattr(settings, section), **values)})
