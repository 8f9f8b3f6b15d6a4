"""The live core: pure, synchronous, no asyncio, viser or FastAPI (see :mod:`app.live.core`).

- :mod:`.session`: a stream on show and its counters;
- :mod:`.ensemble`: the estimator instances stepped together, one batch run per chunk;
- :mod:`.changes`: a PATCH body or a preset -> a validated change;
- :mod:`.history`: the plots' rings with named columns;
- :mod:`.views`: the read models (snapshot, state, decisions, latency figures);
- :mod:`.core`: :class:`LiveCore`, the one object the async shell drives.
"""

from app.live.ensemble import Ensemble, EnsembleError, Instance, Records
from app.live.changes import Change, PatchError, Variant
from app.live.core import LiveCore
from app.live.history import History, Ring, Window
from app.live.session import Session, Totals
from app.live.views import Snapshot

__all__ = ["Ensemble", "EnsembleError", "Change", "History", "Instance", "LiveCore", "PatchError",
           "Records", "Ring", "Session", "Snapshot", "Totals", "Variant", "Window"]
