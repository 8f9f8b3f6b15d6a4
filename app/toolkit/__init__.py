"""The lab session's tools: plain functions and small services on samples, recordings
and estimator parameters (calibration, magnetometer calibration, injected disturbances,
what-if re-runs, recordings, variants). No FastAPI, no viser: the server wires them."""
