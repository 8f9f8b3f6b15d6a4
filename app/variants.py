"""Variants: a second instance of an estimator with its own parameters.

``robust-no-rejection`` (the primary with every gate off, for the disturbance
demonstration) and ``lab-approx`` (exercise 9: the approximate time update (2k) beside
the exact one (2j)) are the ready-made ones; any ``(name, base, params)`` is accepted.
Which parameters are gates is read from the parameter set itself (a gate, band or
de-weighting field whose help says ``0: off``), so a renamed or new gate is covered without a list here.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

from .estimators import NAMES, estimator_class, make_estimator
from .params import ParamError

NAME_RE = re.compile(r"^[a-z][a-z0-9_-]{0,39}$")


class VariantError(ValueError):
    def __init__(self, field_name: str, reason: str):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason


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


def validate(name: str, base: str, params: dict[str, Any] | None,
             existing: set[str] = frozenset()) -> tuple[str, str, dict[str, Any]]:
    """Check a variant request; VariantError names the bad field."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise VariantError("name", "1-40 lowercase letters, digits, '-' or '_', starting "
                                   f"with a letter; got {name!r}")
    if name in existing or name in NAMES:
        raise VariantError("name", f"an estimator named {name!r} exists already")
    if base not in NAMES:
        raise VariantError("base", f"unknown estimator {base!r} (known: {', '.join(NAMES)})")
    params = dict(params or {})
    try:
        make_estimator(base, params)
    except ParamError as e:
        raise VariantError(f"params.{e.field}", e.reason) from None
    return name, base, params
