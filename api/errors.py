"""Error answers: one body shape for every 4xx/5xx, documented per route in the OpenAPI schema,
and the handlers that produce it.

Every error is `{"detail": ...}`: a sentence for 400/401/403/404/405/409/413/416/429/503, and for 422 either a
sentence (checks the API makes itself, e.g. "params.frames: end 90 is past the scene's 60
frames") or pydantic's list of field errors. Clients and schema-driven fuzzers can rely on it
because `error_responses` puts exactly that shape into the schema.

A fluidcore `InputError` that reaches a route unhandled (a stored camera file the geometry reader
refuses, parameters `service` refuses, ...) is a 422 with its message, the service's `NotFound` a
404, its `Conflict` a 409 and its `OverLimit` (an owner's limit) a 429; any other exception is a bug: a 500 whose detail is only
"internal error (id ...)", its traceback in the API's log under that id (`fluidcore.errors`).

Request JSON is parsed strictly (`StrictJSONRoute`): NaN / Infinity literals and nesting deep
enough to exhaust the parser are a 422 before any model sees them, because Python's `json`
accepts the first and raises RecursionError on the second.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import FastAPI, Request, Response
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.routing import Match

from fluidcore.errors import InputError, internal_error
from service.errors import Conflict, NotFound, OverLimit
from service.storage import StorageError
from api.uploads import ClientGone, UploadRejected

log = logging.getLogger(__name__)


class FieldError(BaseModel):
    """One pydantic validation error: where (`loc`), what (`msg`, `type`)."""

    model_config = ConfigDict(extra="allow")
    loc: list[str | int]
    msg: str
    type: str


class Message(BaseModel):
    detail: str = Field(description="what went wrong, in one sentence")


class ValidationFailure(BaseModel):
    detail: str | list[FieldError] = Field(description="a sentence, or pydantic's field errors")


_DESCRIPTIONS = {
    400: "malformed multipart body",
    401: "missing or invalid API key",
    403: "signed download link invalid or expired",
    404: "no such resource for this API key",
    409: "conflicts with the resource's state (the message says which)",
    413: "request body or an uploaded file over its size limit",
    416: "byte range outside the file",
    422: "invalid input (the message names the field)",
    429: "one of the caller's limits reached (the message says which and how to free room; `Retry-After` where waiting helps)",
    503: "database or storage unavailable; retry after `Retry-After` seconds",
}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The `responses=` entry documenting `codes` with the body shape they really have."""
    return {
        code: {"model": ValidationFailure if code == 422 else Message, "description": _DESCRIPTIONS[code]}
        for code in codes
    }


class JSONRejected(json.JSONDecodeError):
    """A body Python's json would accept (NaN) or crash on (deep nesting), but JSON does not allow."""


def _no_constants(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def strict_json(body: bytes) -> Any:
    """`json.loads` without NaN/Infinity and with deep nesting refused, both as JSONDecodeError
    (FastAPI answers those with a 422)."""
    text = body.decode("utf-8", errors="replace")
    try:
        return json.loads(text, parse_constant=_no_constants)
    except ValueError as exc:
        if isinstance(exc, json.JSONDecodeError):
            raise
        raise JSONRejected(str(exc), text[:200], 0) from None
    except RecursionError:
        raise JSONRejected("JSON nested too deeply", text[:200], 0) from None


class _StrictJSONRequest(Request):
    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = strict_json(await self.body())
        return self._json


class StrictJSONRoute(APIRoute):
    """An APIRoute whose request JSON is parsed by `strict_json`."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def strict_handler(request: Request) -> Response:
            return await handler(_StrictJSONRequest(request.scope, request.receive))

        return strict_handler


def _finite(value: Any) -> Any:
    """`value` with non-finite floats written as strings, so an error that echoes them serialises."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    return value


async def validation_failed(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return JSONResponse({"detail": _finite(jsonable_encoder([_explained(e) for e in exc.errors()]))}, status_code=422)


def _explained(error: dict[str, Any]) -> dict[str, Any]:
    """`error` (pydantic's) with a message a client can act on where pydantic's names its own
    machinery: a body without its "type" ("Unable to extract tag using discriminator 'type'"),
    and a JSON body sent as something else ("Input should be a valid dictionary ...", when the
    client left out Content-Type: application/json)."""
    from service.job_types import JobType

    at_body = tuple(error.get("loc", ())) == ("body",)
    if error.get("type") == "union_tag_not_found" and at_body:
        kinds = ", ".join(member.value for member in JobType if member.writes_run)  # what POST /v1/jobs creates
        return {**error, "msg": f'the job needs its "type": one of {kinds}'}
    if error.get("type") == "model_attributes_type" and at_body and isinstance(error.get("input"), (str, bytes)):
        return {**error, "msg": "the body must be a JSON object, sent with the header Content-Type: application/json "
                                "(curl: -H 'Content-Type: application/json', or --json)"}
    return error


async def upload_rejected(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, UploadRejected)
    return JSONResponse({"detail": str(exc)}, status_code=exc.status_code)


async def input_rejected(request: Request, exc: Exception) -> JSONResponse:
    """What the user can fix, found by fluidcore below a route: the message names the field."""
    return JSONResponse({"detail": str(exc)}, status_code=422)


async def internal_failure(request: Request, exc: Exception) -> JSONResponse:
    """A bug: the client gets an id to quote, never the exception's text (a path, SQL, a stack)."""
    return JSONResponse({"detail": internal_error(log, exc, f"{request.method} {request.url.path}")}, status_code=500)


async def not_found(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=404)


async def conflict(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=409)


async def over_limit(request: Request, exc: Exception) -> JSONResponse:
    """An owner's limit (service.quotas): 429, with `Retry-After` when waiting alone frees room."""
    assert isinstance(exc, OverLimit)
    headers = {"Retry-After": str(exc.retry_after)} if exc.retry_after is not None else None
    return JSONResponse({"detail": str(exc)}, status_code=429, headers=headers)


async def client_gone(request: Request, exc: Exception) -> JSONResponse:
    """The client left before its upload was stored (nginx's 499): nobody reads this answer, the
    point is that nothing was stored."""
    return JSONResponse({"detail": "the client closed the connection; nothing was stored"}, status_code=499)


async def storage_unavailable(request: Request, exc: Exception) -> JSONResponse:
    """Object storage down or full: the request may succeed later, nothing was half-written."""
    return JSONResponse({"detail": f"storage unavailable: {exc}"}, status_code=503, headers={"Retry-After": "1"})


async def database_busy(request: Request, exc: Exception) -> JSONResponse:
    """No pooled database connection came in time: say so (and when to retry) instead of a 500."""
    return JSONResponse({"detail": "database busy; retry shortly"}, status_code=503, headers={"Retry-After": "1"})


HANDLERS: dict[type[Exception], Callable[[Request, Exception], Coroutine[Any, Any, JSONResponse]]] = {
    RequestValidationError: validation_failed,
    UploadRejected: upload_rejected,
    ClientGone: client_gone,
    StorageError: storage_unavailable,
    PoolTimeout: database_busy,
    InputError: input_rejected,
    NotFound: not_found,
    Conflict: conflict,
    OverLimit: over_limit,
    Exception: internal_failure,
}


API_PATHS = ("/v1/{rest:path}", "/healthz", "/readyz")
ALL_METHODS = ["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"]


def add_unmatched_routes(app: FastAPI, routes: list[APIRoute]) -> None:
    """Answer an unknown path (404) or method (405 with the route's real `Allow`) under the API's
    paths in the API's own shape. Without this the web folder mounted at `/` takes every such
    request and answers 405 `Allow: GET, HEAD` for, say, OPTIONS /v1/jobs. Add it after the API
    routers (whose `routes` it is given) and before that mount: the router tries routes in order."""

    async def unmatched(request: Request) -> JSONResponse:
        allowed = sorted({m for r in routes if r.matches(request.scope)[0] == Match.PARTIAL for m in r.methods})
        if allowed:
            return JSONResponse(
                {"detail": f"method {request.method} not allowed; use {', '.join(allowed)}"},
                status_code=405,
                headers={"Allow": ", ".join(allowed)},
            )
        return JSONResponse({"detail": f"no route {request.url.path}"}, status_code=404)

    for path in API_PATHS:
        app.add_api_route(path, unmatched, methods=ALL_METHODS, include_in_schema=False)
