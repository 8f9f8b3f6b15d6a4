"""Pydantic models of the HTTP API (they make the OpenAPI docs at ``/docs``)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class Health(BaseModel):
    status: str = Field(description="'ok' while the filter task runs")
    restarts: int = Field(0, description="times the filter task ended and its supervisor restarted it")
    loop_errors: int = Field(0, description="items the filter task skipped after an error")
    step_errors: int = Field(0, description="samples an estimator raised on (logged, skipped)")
    restored: int = Field(0, description="times an estimator's state went non-finite and its "
                          "last good state was restored")
    dropped_subscribers: int = Field(0, description="WS /ws/state clients dropped for not reading")
    source: str
    estimators: list[str]
    primary: str
    filters: dict[str, str] = Field(default_factory=dict, description=
                                    "each filter's readiness: 'ready', 'compiling' (numba, "
                                    "after an install or an update), 'waiting' (its turn to "
                                    "compile) or 'failed'; samples are filtered once all are ready")
    ready: bool = Field(True, description="every filter is ready (compiled or loaded)")


class Info(BaseModel):
    """What the landing page needs to embed the viewer and explain the phone set-up."""
    viewer_port: int
    phone_port: int | None = Field(None, description="the Sensor Fusion app's TCP port "
                                   "(presenter only: watchers are not told how to connect)")
    lan_ip: str | None = Field(None, description="the PC's address for phones (presenter only)")
    source: str
    presenter: bool = Field(False, description="this browser holds the presenter's token "
                            "(or the server runs with --open): it may change the session")
    viewer_token: str | None = Field(None, description="for the presenter only: the token "
                                     "the page passes to the embedded viewer")


class Decision(BaseModel):
    """How the primary estimator treated the last sample of a sensor."""
    reason: str = Field(description="used, norm, nis, dip, field, disabled, absent, wait, ...")
    text: str
    rejected: bool = Field(description="a valid sample refused by a gate")
    value: float | None = Field(None, description="the value the gate tested (norm m/s² or µT, "
                                "L_k µT, dip rad, NIS)")
    nis: float | None = None
    t: float | None = None


class EstimatorState(BaseModel):
    q: list[float]
    euler_deg: list[float]
    base: str = Field(description="the estimator kind (a variant's base)")
    initialized: bool
    error_to_phone_deg: float | None
    error_to_truth_deg: float | None
    acc: Decision
    mag: Decision
    gyr_bias: list[float] | None
    step_errors: int = 0
    restored: int = 0


class State(BaseModel):
    """The state after the last processed sample."""
    model_config = ConfigDict(extra="allow")
    t: float | None = Field(description="s, the phone's clock as sent: time_ms/1000 of the last "
                            "processed sample (on the clock of the stream's first motion tag)")
    source: str = Field(description="demo, phone, phone-disconnected, replay or none")
    status: str = Field(description="the source in words, as the GUI shows it")
    primary: str
    q: list[float] = Field(description="[w, x, y, z] of the primary estimator, sensor to world (ENU)")
    euler_deg: list[float] = Field(description="[yaw, pitch, roll] by the manual's q2euler, degrees")
    initialized: bool
    phone_q: list[float] | None = Field(description="the phone's own estimate (ORI) or null")
    phone_euler_deg: list[float] | None
    truth_q: list[float] | None = Field(description="ground truth (demo only) or null")
    error_to_phone_deg: float | None = Field(description="formula (2c) between q and phone_q")
    error_to_truth_deg: float | None
    acc_rejected: bool
    mag_rejected: bool
    acc: Decision
    mag: Decision
    standstill: bool
    sigma_deg: list[float] | None = Field(description="1σ attitude uncertainty about E, N, Up")
    diagnostics: dict[str, Any] = Field(description="the primary estimator's Diagnostics (app.estimators."
                                        "base.Diagnostics), every field by name: references, "
                                        "gate bands and gates, learned state; null where "
                                        "the estimator has no such thing")
    silent_s: float | None = Field(None, description="a connected phone that has sent no "
                                   "samples for 3 s or more: for how long (s, PC clock); "
                                   "null otherwise")
    rates_hz: dict[str, float | None] = Field(description="per sensor tag (ACC, GYR, MAG, ORI): "
                                              "its rate; 0: it stopped while the stream goes on; "
                                              "null: not yet known")
    withheld: dict[str, str] = Field(default_factory=dict, description="a sensor the phone sends "
                                     "and orientlab holds back, with why (Sensor Logger's "
                                     "orientation until its convention is checked); it has no "
                                     "rate meanwhile")
    counts: dict[str, Any] = Field(description="lines, samples, malformed (+ by reason), late, "
                                   "clamped, jumps (the clock re-anchored), tags, updates per "
                                   "estimator and sensor, totals")
    clock_offsets_s: dict[str, float]
    estimators: dict[str, EstimatorState]


class Params(BaseModel):
    """The parameters (SI units): the primary, the switches every estimator shares
    (values of the primary) and each estimator's full set."""
    model_config = ConfigDict(extra="allow")
    primary: str
    estimators: dict[str, dict[str, Any]]


class PresetRequest(BaseModel):
    name: str | None = Field(None, description="letters, digits, '-' or '_'", examples=["lecture-3"])
    path: str | None = Field(None, description="load only: a preset file on this PC (e.g. written "
                             "by orientlab calibrate)", examples=["~/calib/pixel7.toml"])


PATCH_DOC = """A partial JSON object; every field is validated before anything is applied
(an unknown key or an out-of-range value: 422 naming the field, nothing applied). Values in SI
units (rad/s, m/s², µT, s), as in GET /api/params.

- a top-level parameter must be a **shared** one (`use_gyr`, `use_acc`, `use_mag`, `max_gap`,
  `gyr_hold`, `gyr_bias`, `acc_band_rel`: one meaning and unit in every estimator); it
  applies to **every** estimator that has it. Any other goes under `estimators`;
- a renamed key is refused naming its new name (e.g. `gyr_noise was renamed gyr_std in lab`);
- `primary`: the estimator drawn and plotted (`robust`, `lab`, `complementary`, `phone`);
- `estimators`: `{"<estimator>": {"<param>": value}}` for one estimator (wins over top level);
- `reset`: `true` forgets the orientation (the filters align again).

Changes apply from the next sample on. The response is the new GET /api/params."""

PATCH_EXAMPLES = {
    "magnetometer off": {"value": {"use_mag": False}},
    "lab filter, approximate time update": {
        "value": {"primary": "lab", "estimators": {"lab": {"time_update": "approx", "acc_std": 0.3}}}},
}
