"""The one error every tool's service raises for a refused request."""

from __future__ import annotations


class ToolError(ValueError):
    """A refused request: ``field`` names the key (a dotted path for a nested one),
    ``reason`` says why, ``status`` what kind of refusal it is in HTTP terms (404 unknown,
    409 not now, 422 invalid; 507 a folder that refused a write). The server maps it to
    an answer in one place; the page shows it as a notification."""

    def __init__(self, field_name: str, reason: str, status: int = 422):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason
        self.status = status
