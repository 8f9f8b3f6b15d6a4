"""``robust``: orientlab's default estimator, an error-state EKF built for real phones.

Structure (4c) of the lab manual (gyroscope as input, its bias in the state) in the
error-state (multiplicative) form: the nominal attitude ``q`` is a unit quaternion; the
filter's state is the small rotation ``δθ`` (world frame, ``q_true = exp(δθ) ⊗ q``) and
the gyroscope bias ``b`` (sensor frame), 6 states with a well-conditioned 6x6 ``P``
(no covariance along the unit-norm constraint, no renormalisation hack).

What makes it accurate on real data (see ``shared/notes/robust-orientation.md``), each
explained in the module that does it:

- :mod:`.tilt`: **tilt from an inertial low-pass of the accelerometer** (it corrects the
  tilt only, never the heading), **a damped tilt loop** (``tilt_damping``), **specific force
  flagged** (ACCEL), **the accelerometer's lag** (``acc_delay_periods``: half its sample period).
- :mod:`.kernel` (the time update): **scale-factor noise along the net turn**
  (``gyr_scale_noise``), **the heading's σ grows with the turn while the field is
  refused** (``refused_turn_noise``), the reset of an implausible bias (``bias_max``).
- :mod:`.heading`: **heading only from the magnetometer**, **magnetic disturbance
  detection** (VQF's logic), **the field turn test**, **the heading's noise measured from
  the data** (``heading_evidence_tau``: the field's wander against the gyroscope slows the
  correction; docs/filter.md), **never lost** (RECOVER).
- :mod:`.bias`: **rest detection** (a steady spin above ``bias_max`` is no rest), **bias in
  motion from the correction rates**.
- :mod:`.hardiron`: **a sensor-fixed magnetic offset tracked online** (a magnet on the
  phone: a causal sphere fit, applied only when the corrected field is the earth's; flag
  OFFSET, ``Diagnostics.mag_offset``); :mod:`.heading` also makes **a return to the field
  after a refusal wait for evidence** (consistent over a quarter turn) and compensates
  **the field's delay** (``mag_delay``).
- **Measurement noise as densities** (``tilt_noise``, ``heading_noise`` in rad·√s):
  ``R = σ²/Δt`` per update, so the correction time constants, ``tilt_noise /
  gyr_noise`` and ``heading_noise / gyr_noise``, do not depend on the sample rates.

Every update goes through :func:`app.estimators.kalman.correct`. The per-row code is
numba-compiled (``robust_step``); ``robust_run`` loops it over arrays for batch
use. The same functions run uncompiled (``.py_func``) as the readable numpy reference.
The kernels read the parameters, the coefficients derived from them and the state from
two flat arrays whose slots are named once (``PRM`` in :mod:`.params`, ``S`` in
:mod:`.state`).

The modules: :mod:`.params` (the parameters, the parameter vector), :mod:`.state` (the
state vector, and the kernels every update uses on it: the error-state injection, the
low-pass coefficient, the update-rate accumulator), :mod:`.bias`, :mod:`.tilt`,
:mod:`.heading` (the mechanisms), :mod:`.kernel` (time update, alignment, one row, a
batch), :mod:`.estimator` (the :class:`RobustEKF` class).
"""

from __future__ import annotations

from app.estimators.robust.bias import BIAS_UPD_S, H_BIAS, heading_drift_update, motion_bias_update, rest_update
from app.estimators.robust.estimator import RobustEKF
from app.estimators.robust.hardiron import HI_STATUS, hard_iron, hard_iron_reset, strength_deviations
from app.estimators.robust.heading import heading_innovation, heading_jacobian, mag_update
from app.estimators.robust.kernel import robust_run, robust_step
from app.estimators.robust.params import (DERIVED, NPARAM, PRM, RobustParams, derived, layout,
                                          param_vector)
from app.estimators.robust.state import (DT_MAX, NSTATE, S, STATE, STATE_NAN, inject, lp_coef, new_state,
                                         rotate3, update_is_due)
from app.estimators.robust.tilt import acc_update, tilt_innovation, tilt_jacobian

__all__ = ["HI_STATUS", "hard_iron", "hard_iron_reset", "strength_deviations", "BIAS_UPD_S", "DERIVED", "DT_MAX", "H_BIAS", "NPARAM", "NSTATE", "PRM", "RobustEKF",
           "RobustParams", "S", "STATE", "STATE_NAN", "acc_update", "derived", "heading_drift_update",
           "heading_innovation", "heading_jacobian", "inject", "layout", "lp_coef", "mag_update",
           "motion_bias_update", "new_state", "param_vector", "rest_update", "robust_run", "robust_step",
           "rotate3", "tilt_innovation", "tilt_jacobian", "update_is_due"]
