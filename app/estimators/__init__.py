"""The estimators, by name. ``DEFAULT`` is the one used when none is named."""

from __future__ import annotations

from typing import Any

from app.jitcache import ensure_fresh

ensure_fresh()   # before base.py, which runs compiled code on import (see app.jitcache)

from app.estimators.base import (ALERTS, AVERAGED_IN, BatchResult, Diagnostics, Estimator, FLAG_COLUMNS, Reason, REASON_TEXT,
                   REJECTIONS, StepFlags, TimeIssue, count_flags, is_rejected)

DEFAULT = "robust"
NAMES = ("robust", "lab", "complementary", "phone")


def estimator_class(name: str) -> type[Estimator]:
    if name == "robust":
        from app.estimators.robust import RobustEKF
        return RobustEKF
    if name == "lab":
        from app.estimators.lab import LabEKF
        return LabEKF
    if name == "complementary":
        from app.estimators.complementary import ComplementaryDNRF
        return ComplementaryDNRF
    if name == "phone":
        from app.estimators.phone import PhoneOrientation
        return PhoneOrientation
    raise KeyError(f"unknown estimator {name!r} (known: {', '.join(NAMES)})")


def make_estimator(name: str = DEFAULT, params: dict[str, Any] | None = None) -> Estimator:
    """A fresh estimator ``name`` with its defaults changed by ``params`` (validated)."""
    cls = estimator_class(name)
    return cls(**(params or {}))


__all__ = ["ALERTS", "AVERAGED_IN", "BatchResult", "Diagnostics", "Estimator", "FLAG_COLUMNS", "Reason", "REASON_TEXT", "REJECTIONS",
           "StepFlags", "TimeIssue", "count_flags", "is_rejected", "DEFAULT", "NAMES", "estimator_class",
           "make_estimator"]
