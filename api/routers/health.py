"""`/healthz`: the process answers. `/readyz`: the database, the broker and storage answer too."""

from __future__ import annotations

from collections.abc import Callable

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from api.schemas import Health
from service.database import ping

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Health, responses={503: {"model": Health}})
def readyz(request: Request) -> JSONResponse:
    state = request.app.state
    checks: dict[str, Callable[[], None]] = {
        "database": lambda: ping(state.engine),
        "broker": state.queue.ping,
        "storage": state.storage.check,
    }
    results: dict[str, str] = {}
    for name, check in checks.items():
        try:
            check()
            results[name] = "ok"
        except Exception as exc:  # report every failing dependency, whatever it raised
            results[name] = f"error: {exc}"
    ready = all(value == "ok" for value in results.values())
    body = Health(status="ok" if ready else "unavailable", checks=results)
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503)
