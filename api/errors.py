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

import difflib
import json
import logging
import math
import types
import typing
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import FastAPI, Request, Response
from fastapi import params as fastapi_params
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
    route = request.scope.get("route")
    sent = request.headers.get("content-type", "").split(";")[0].strip().lower()
    explained = [_explained(e, route if isinstance(route, APIRoute) else None, sent) for e in exc.errors()]
    return JSONResponse({"detail": _finite(jsonable_encoder(explained))}, status_code=422)


def _explained(error: dict[str, Any], route: APIRoute | None, sent: str) -> dict[str, Any]:
    """`error` (pydantic's) with a message a client can act on where pydantic's names its own
    machinery: a body without its "type" ("Unable to extract tag using discriminator 'type'") or
    with a type that is none ("Input tag ... does not match"), a JSON body sent as something else
    ("Input should be a valid dictionary ...", when the client left out Content-Type:
    application/json), JSON sent to a form route ("Field required" at body.video: the route takes
    multipart/form-data), and a misspelt field ("Extra inputs are not permitted": which are
    allowed there). `route` is the route that refused the request, `sent` the request's media type."""
    at_body = tuple(error.get("loc", ())) == ("body",)
    kind = error.get("type")
    if kind in ("union_tag_not_found", "union_tag_invalid") and at_body:
        return {**error, "msg": _job_type_message(error)}
    if kind == "model_attributes_type" and at_body and isinstance(error.get("input"), (str, bytes)):
        return {**error, "msg": "the body must be a JSON object, sent with the header Content-Type: application/json "
                                "(curl: -H 'Content-Type: application/json', or --json)"}
    form = _form_fields(route)
    if form and sent not in FORM_MEDIA_TYPES and error.get("loc", ("",))[0] == "body":
        return {**error, "msg": _form_message(route, form, sent)}
    if kind == "extra_forbidden" and route is not None:
        allowed = _allowed_fields(route, tuple(error.get("loc", ()))[:-1])
        if allowed:
            return {**error, "msg": f"{error['msg']}: {_unknown_field_message(str(error['loc'][-1]), allowed)}"}
    return error


# The media types of a form body (what a route of Form and File parameters reads).
FORM_MEDIA_TYPES = ("multipart/form-data", "application/x-www-form-urlencoded")


def _job_type_message(error: dict[str, Any]) -> str:
    """What a job request without a valid "type" should send: the types `POST /v1/jobs` creates,
    and where the others (a render, a bundle) are asked for."""
    from service.job_types import JobType

    kinds = ", ".join(member.value for member in JobType if member.writes_run)
    sent = (error.get("ctx") or {}).get("tag")
    if sent is None:
        return f'the job needs its "type": one of {kinds}'
    others = [member.value for member in JobType if not member.writes_run]
    return (f'"type" is {sent!r}, not a job type POST /v1/jobs creates: give one of {kinds} '
            f"({' and '.join(others)} jobs are asked for at POST /v1/jobs/ID/videos/NAME and /bundles)")


def _form_fields(route: APIRoute | None) -> dict[str, bool]:
    """The form parts a route reads (name -> required), in its declared order; empty for a route
    whose body is JSON (or that has none)."""
    if route is None:
        return {}
    return {field.alias: field.field_info.is_required() for field in route.dependant.body_params
            if isinstance(field.field_info, fastapi_params.Form)}


def _form_message(route: APIRoute, form: dict[str, bool], sent: str) -> str:
    """A form route sent something else (JSON, usually): what it takes instead, each part named."""
    files = {field.alias for field in route.dependant.body_params if isinstance(field.field_info, fastapi_params.File)}

    def part(name: str) -> str:
        return f"{name} (a file)" if name in files else name

    required = [part(name) for name, needed in form.items() if needed]
    optional = [part(name) for name, needed in form.items() if not needed]
    return (f"{', '.join(sorted(route.methods))} {route.path} takes multipart/form-data (one part per field; curl: -F NAME=VALUE, "
            f"-F NAME=@FILE), not {sent or 'a body without Content-Type'}: required: {', '.join(required)}; "
            f"optional: {', '.join(optional)}")


def _unknown_field_message(name: str, allowed: list[str]) -> str:
    """"'qualty' is not a field here (did you mean 'quality'?); allowed: ..."."""
    close = difflib.get_close_matches(name, allowed, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{name!r} is not a field here{hint}; allowed: {', '.join(allowed)}"


def _allowed_fields(route: APIRoute, loc: tuple[str | int, ...]) -> list[str]:
    """The field names of the model at `loc` (a validation error's location, "body" first) in the
    route's body: what may stand where a forbidden extra field was sent. Empty when `loc` does not
    lead to one model."""
    if not loc or loc[0] != "body":
        return []
    for field in route.dependant.body_params:
        for path in (loc[1:], loc[2:] if loc[1:2] == (field.alias,) else None):
            model = None if path is None else _model_at(field.field_info.annotation, path)
            if model is not None:
                return sorted(info.alias or name for name, info in model.model_fields.items())
    return []


def _model_at(annotation: Any, path: tuple[str | int, ...]) -> type[BaseModel] | None:
    """The pydantic model reached from `annotation` along `path`: field names into models, the tag
    of a discriminated union's member, indices into lists and tuples, keys into dicts."""
    for step in path:
        nexts = [found for member in _members(annotation) if (found := _step(member, step)) is not None]
        if len(nexts) != 1:
            return None
        annotation = nexts[0]
    models = [m for m in _members(annotation) if isinstance(m, type) and issubclass(m, BaseModel)]
    return models[0] if len(models) == 1 else None


def _members(annotation: Any) -> list[Any]:
    """The types `annotation` may be: Annotated unwrapped, a union (an Optional too) split, None left out."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _members(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [m for arg in typing.get_args(annotation) for m in _members(arg)]
    return [] if annotation is type(None) else [annotation]


def _step(member: Any, step: str | int) -> Any:
    """One step of `_model_at` from one type: a model's field (by name or alias), or the model
    itself when `step` is its discriminator's tag; a container's element type; else None."""
    if isinstance(member, type) and issubclass(member, BaseModel):
        for name, info in member.model_fields.items():
            if step in (name, info.alias):
                return info.annotation
            if typing.get_origin(info.annotation) is typing.Literal and typing.get_args(info.annotation) == (step,):
                return member
        return None
    origin, args = typing.get_origin(member), typing.get_args(member)
    if isinstance(step, int) and origin in (list, set, frozenset) and args:
        return args[0]
    if isinstance(step, int) and origin is tuple and args:
        return args[0] if args[-1] is Ellipsis else args[step] if step < len(args) else None
    if isinstance(step, str) and origin is dict and len(args) == 2:
        return args[1]
    return None


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
