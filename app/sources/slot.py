"""The phone slot: one phone at a time, across every app, with the presenter in charge.

A classroom has thirty phones and one projector. Whichever app a phone uses (the Sensor
Fusion app over TCP, Sensor Logger or phyphox pushing over HTTP, phyphox polled), it must
hold the slot to be shown:

- a phone **takes** the slot with its first valid sample while the slot is free;
- a second phone (of any app) is **refused** while the holder has sent a valid sample
  within ``idle_s`` seconds; the refusal is a sentence its app can show (Sensor Logger
  shows the text of a 499 reply; phyphox shows a network error; the TCP app is closed);
- a holder silent for ``idle_s`` seconds may be **taken over** by the next phone;
- the presenter may **lock** the slot (no new phone at all) and **release** the holder:
  its stream ends at once and the same phone is kept out for ``release_s`` seconds, so a
  stray client that trickles one sample every two seconds cannot hold the projector.

Pure: no I/O, no asyncio; the clock is injectable. Each holder brings an ``on_release``
callback (close the TCP connection, end the push stream) that the slot calls when the
holder is released or taken over.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

#: the apps that can hold the slot, with the words shown for them
PHONE_APPS = {"sensorfusion": "Sensor Fusion app", "sensorlogger": "Sensor Logger",
        "phyphox": "phyphox", "phyphox-poll": "phyphox (remote access)"}
TURNED_AWAY_S = 60.0     # a phone turned away is listed in the status for this long
TURNED_AWAY_KEPT = 8     # at most this many (the latest)


@dataclass
class Holder:
    phone_app: str              # a key of PHONE_APPS
    key: str                    # who it is: a TCP peer, a device id, a phone URL
    label: str                  # shown on the page
    since: float
    last_valid: float
    on_release: Callable[[str], None] | None = field(default=None, repr=False)
    who: str = ""               # the phone kept out when released (take() sets it: the key if none)
    idle_s: float = 0.0         # its own silence allowance, if longer than the slot's (a push
                                # app sending a batch every few seconds: touch() sets it)


class PhoneSlot:
    """See the module doc. ``clock``: monotonic seconds (tests give their own)."""

    def __init__(self, idle_s: float = 3.0, release_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic):
        self.idle_s = float(idle_s)
        self.release_s = float(release_s)
        self.clock = clock
        self.locked = False
        self.holder: Holder | None = None
        self.refused = 0                # requests refused (busy, locked or released)
        self.released = 0               # holders released by the presenter
        self.last_refusal = ""
        # the phones turned away lately, each once: (app, address) -> [times, last, why]
        self._turned_away: dict[tuple[str, str], list] = {}
        self._banned: dict[str, float] = {}    # key -> until (monotonic)

    # ------------------------------------------------------------------ queries
    def busy(self) -> bool:
        """A holder that has sent a valid sample within ``idle_s`` (or its own allowance,
        if longer: a phone that sends a batch every 5 s is not silent between them)."""
        h = self.holder
        return h is not None and self.clock() - h.last_valid < self.allowance(h)

    def allowance(self, h: Holder) -> float:
        """How long holder ``h`` may be silent before another phone may take over."""
        return max(self.idle_s, h.idle_s)

    def holds(self, key: str) -> bool:
        return self.holder is not None and self.holder.key == key

    def refusal(self, phone_app: str, key: str, who: str = "") -> str | None:
        """Why a phone (``phone_app``, ``key``; ``who``: its address if the key is more, as
        a TCP peer's port) may not take the slot now, in words its user can read; None if
        it may (free, silent holder, or it is the holder)."""
        if self.holds(key):
            return None
        now = self.clock()
        who = who or key
        until = self._banned.get(who)
        if until is not None:
            if now < until:
                return ("orientlab: the presenter released this phone; it may stream again "
                        f"in {until - now:.0f} s")
            del self._banned[who]
        if self.locked:
            return "orientlab: the presenter has locked the phone slot; no new phone is accepted"
        if self.busy():
            name = PHONE_APPS.get(self.holder.phone_app, self.holder.phone_app)
            return (f"orientlab: another phone ({name}) is streaming; keep sending: this "
                    f"phone takes over once that one has been silent for "
                    f"{max(self.idle_s, self.holder.idle_s):g} s")
        return None

    # ------------------------------------------------------------------ changes
    def count_refusal(self, why: str, phone_app: str = "", who: str = "") -> None:
        """A phone (``phone_app`` from address ``who``) was turned away with ``why`` (by
        whichever receiver): the slot's status counts it, shows the last reason (the Connect
        tab's "refused N×") and lists the phones turned away lately (``turned_away``), so
        the presenter sees which phone waits and why."""
        self.refused += 1
        self.last_refusal = why
        if not who:
            return
        key = (phone_app, who)
        rec = self._turned_away.pop(key, None) or [0, 0.0, ""]
        rec[0] += 1
        rec[1], rec[2] = self.clock(), why
        self._turned_away[key] = rec          # the newest last
        while len(self._turned_away) > TURNED_AWAY_KEPT:
            del self._turned_away[next(iter(self._turned_away))]

    def turned_away(self) -> list[dict]:
        """The phones turned away within :data:`TURNED_AWAY_S`, the latest first: app,
        address, how many times, how long ago and the last reason."""
        now = self.clock()
        return [{"app": a, "app_name": PHONE_APPS.get(a, a), "who": who, "times": n,
                 "ago_s": round(now - t, 1), "why": why}
                for (a, who), (n, t, why) in reversed(self._turned_away.items())
                if now - t < TURNED_AWAY_S]

    def take(self, phone_app: str, key: str, label: str,
             on_release: Callable[[str], None] | None = None, who: str = "") -> str | None:
        """Take the slot (a silent holder is released first, taken over). Returns the
        refusal (nothing changed) or None. Taking it again as the holder only refreshes.
        ``who``: the phone a release keeps out, if not ``key`` (a TCP phone reconnects from
        another port: its address)."""
        why = self.refusal(phone_app, key, who)
        if why is not None:
            self.count_refusal(why, phone_app, who or key)
            return why
        now = self.clock()
        if self.holds(key):
            self.holder.last_valid = now
            return None
        if self.holder is not None:
            self._drop(f"silent for {self.allowance(self.holder):g} s, taken over by another phone "
                       f"({PHONE_APPS.get(phone_app, phone_app)})")
        self.holder = Holder(phone_app, key, label, now, now, on_release, who or key)
        return None

    def touch(self, key: str, idle_s: float | None = None) -> None:
        """The holder sent a valid sample; ``idle_s``: its own silence allowance from now
        on (its batches' period and more), if it knows one."""
        if self.holds(key):
            self.holder.last_valid = self.clock()
            if idle_s is not None:
                self.holder.idle_s = float(idle_s)

    def leave(self, key: str) -> None:
        """The holder's stream ended by itself (EOF, stream stopped): the slot is free."""
        if self.holds(key):
            self.holder = None

    def release(self, reason: str = "released by the presenter") -> str | None:
        """The presenter frees the slot: the holder's stream ends and the same phone is
        kept out for ``release_s`` seconds. Returns the released holder's label."""
        h = self.holder
        if h is None:
            return None
        self._banned[h.who] = self.clock() + self.release_s
        self.released += 1
        self._drop(reason)
        return h.label

    def _drop(self, reason: str) -> None:
        h, self.holder = self.holder, None
        if h is not None and h.on_release is not None:
            try:
                h.on_release(reason)
            except Exception:   # a holder's bug must not keep the slot taken
                pass

    def status(self) -> dict:
        h = self.holder
        now = self.clock()
        return {"locked": self.locked,
                "holder": None if h is None else {
                    "app": h.phone_app, "app_name": PHONE_APPS.get(h.phone_app, h.phone_app),
                    "label": h.label,
                    "for_s": round(now - h.since, 1),
                    "silent_s": round(now - h.last_valid, 1)},
                "busy": self.busy(), "refused": self.refused, "released": self.released,
                "last_refusal": self.last_refusal or None, "turned_away": self.turned_away()}
