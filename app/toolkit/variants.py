"""Variants: a second instance of an estimator with its own parameters.

``robust-no-rejection`` (the primary with every gate off, for the disturbance
demonstration) and ``lab-approx`` (exercise 9: the approximate time update (2k) beside
the exact one (2j)) are the ready-made ones; any ``(name, base, params)`` is accepted
(``app.live.bench.Bench.check_new`` validates it).
Which parameters are gates is read from the parameter set itself (a gate, band or
de-weighting field whose help says ``0: off``), so a renamed or new gate is covered without a list here.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from app.estimators import estimator_class


def no_rejection_changes(base: str) -> dict[str, Any]:
    """The parameter changes that turn off every gate of estimator ``base``: fields
    named ``*gate*``, ``*band*`` or ``*dev_weight*`` (a deviating field trusted less)
    whose help says ``0: off`` get 0; optional absolute bands (``*_band_uT``) get None."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(estimator_class(base).Params):
        name, meta = f.name, f.metadata
        if not any(k in name for k in ("gate", "band", "dev_weight")):
            continue   # gates, bands and the de-weighting of a deviating field
        if meta.get("optional") and name.endswith("_uT"):
            out[name] = None
        elif "0: off" in (meta.get("doc") or ""):
            out[name] = 0.0 if not meta.get("integer") else 0
    return out


def ready_made(primary: str) -> dict[str, tuple[str, dict[str, Any]]]:
    """The variants the page offers with one click: ``{name: (base, params)}``."""
    out = {f"{primary}-no-rejection": (primary, no_rejection_changes(primary))}
    out["lab-approx"] = ("lab", {"time_update": "approx"})
    return out
