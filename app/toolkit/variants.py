"""Variants: a second instance of an estimator with its own parameters.

``robust-no-rejection`` (the primary with every gate off, for the disturbance
demonstration) and ``lab-approx`` (exercise 9: the approximate time update (2k) beside
the exact one (2j)) are the ready-made ones; any ``(name, base, params)`` is accepted
(``app.live.ensemble.Ensemble.check_new`` validates it).
Which parameters are gates is read from the parameter set itself (each declares it:
``param(rejects=True)``), so a renamed or new gate is covered without a list here.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from app.estimators import estimator_class
from app.toolkit.errors import ToolError


def no_rejection_changes(base: str) -> dict[str, Any]:
    """The parameter changes that turn off every gate of estimator ``base``: each parameter
    whose metadata says it rejects or de-weights a sensor's data (``param(rejects=True)``: a
    gate, a band, the heading noise added for a deviating or wandering field) goes to its off
    value, 0, or None for an optional one."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(estimator_class(base).Params):
        meta = f.metadata
        if not meta.get("rejects"):
            continue
        if meta.get("optional"):
            out[f.name] = None
        else:
            out[f.name] = 0 if meta.get("integer") else 0.0
    return out


#: the ready-made variants the page and ``POST /api/estimators {"preset": ...}`` offer
PRESETS = ("no-rejection", "lab-approx")


def preset(key: str, primary: str) -> tuple[str, str, dict[str, Any]]:
    """A ready-made variant (:data:`PRESETS`) as ``(name, base, params)``, ``primary``
    the estimator on show: ``no-rejection`` it with every gate off, ``lab-approx`` the lab
    filter with the approximate time update; ToolError for another key."""
    if key == "no-rejection":
        return f"{primary}-no-rejection", primary, no_rejection_changes(primary)
    if key == "lab-approx":
        return "lab-approx", "lab", {"time_update": "approx"}
    raise ToolError("preset", f"one of {', '.join(PRESETS)}")


def ready_made(primary: str) -> dict[str, tuple[str, dict[str, Any]]]:
    """Every ready-made variant for the estimator ``primary``: ``{name: (base, params)}``
    (the benchmarks add them to measure the cost of variants)."""
    out = {}
    for key in PRESETS:
        name, base, params = preset(key, primary)
        out[name] = (base, params)
    return out


class VariantService:
    """Variants on the live ensemble: checks an instance to add or remove before the
    server posts the change (the ensemble applies it between two chunks). ``core``: the
    live core."""

    def __init__(self, core):
        self.core = core

    def check_add(self, name: str, base: str, params: dict[str, Any] | None) -> dict[str, Any]:
        """``params`` (a copy) if ``name`` may be added as a variant of ``base``, else
        ToolError naming the field (``name``, ``base``, ``params`` or ``params.<key>``)."""
        try:
            self.core.ensemble.check_new(name, base, params)
        except Exception as e:  # EnsembleError or ParamError: both name the field
            fld = getattr(e, "field", "params")
            if fld not in ("name", "base", "params"):
                fld = f"params.{fld}"
            raise ToolError(fld, getattr(e, "reason", str(e))) from None
        return dict(params or {})

    def preset(self, key: str) -> tuple[str, str, dict[str, Any]]:
        """A ready-made variant (:data:`PRESETS`) as ``(name, base, params)``:
        ``no-rejection`` the primary with every gate off, ``lab-approx`` the lab filter
        with the approximate time update; ToolError for another key."""
        return preset(key, self.core.ensemble.base_of(self.core.ensemble.primary))

    def check_remove(self, name: str) -> str:
        """``name`` if it is a variant on the ensemble, else ToolError (404 or 409)."""
        b = self.core.ensemble
        if name not in b.names:
            raise ToolError("name", f"no estimator {name!r} (known: {', '.join(b.names)})", 404)
        if b.base_of(name) == name:
            raise ToolError("name", f"{name} is built in and cannot be removed", 409)
        return name

    def variants(self) -> list[str]:
        """The variants on the ensemble, in the order they were added."""
        b = self.core.ensemble
        return [n for n in b.names if b.base_of(n) != n]

    def listing(self) -> dict[str, Any]:
        """``GET /api/estimators``: the primary and every instance."""
        b = self.core.ensemble
        return {"primary": b.primary, "estimators": [
            {"name": n, "base": b.base_of(n), "builtin": b.base_of(n) == n} for n in b.names]}
