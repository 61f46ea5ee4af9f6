"""What the service's operations refuse, told apart by kind so each caller answers in its own
terms (the API: 404, 409, 422; the worker: a log line) without the service knowing HTTP."""

from __future__ import annotations

from fluidcore.errors import InputError


class NotFound(LookupError):
    """A job, scene or artifact that does not exist, or is not the caller's: the two are one
    answer, so ids are never disclosed."""

    @classmethod
    def named(cls, kind: str, ident: str) -> NotFound:
        """`kind` ("job", "scene") `ident` not found; an empty id is said to be empty (a client that
        sent "" read "scene  not found", two spaces and no hint)."""
        if not ident.strip():
            return cls(f"{kind} id is empty: give the id of one of your {kind}s (GET /v1/{kind}s lists them)")
        return cls(f"{kind} {ident} not found")


class Conflict(Exception):
    """A request that the state of what it names refuses now (a job still running, a scene still
    used); the message says which."""


class RefusedParams(InputError):
    """Parameters that do not fit what they refer to (a frame past the scene's, a ball outside the
    parent run's box); the message names the field."""


class DuplicateRequest(Exception):
    """A concurrent request with the same Idempotency-Key stored its row first; nothing of this
    one was kept (the caller answers with that row)."""


class OverLimit(Exception):
    """The owner reached one of their limits (`service.quotas`); the message names it and how to
    free room. `retry_after`: seconds after which waiting alone may help (None: only deleting
    something does)."""

    def __init__(self, message: str, retry_after: int | None = None) -> None:
        super().__init__(message)
        self.retry_after = retry_after
