"""What a session raises: each error's message says why and what to do, in one line."""

from __future__ import annotations

__all__ = ["SessionError", "MismatchError", "CapacityError", "SyncConflictError"]


class SessionError(Exception):
    """The session cannot go on as asked; the message says why and what to do (one line)."""


class MismatchError(SessionError, ValueError):
    """What the host was told (layout, lattice, --fd, ...) does not match the sheet it found."""


class CapacityError(MismatchError):
    """The traffic asked for does not fit a bus (docs/protocol.md §10)."""


class SyncConflictError(SessionError):
    """Another SYNC source drives the sheet while the host was asked to drive it."""
