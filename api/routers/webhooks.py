"""`/v1/webhook-secret`: the key that signs the caller's job webhooks (service.webhooks)."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from api.deps import OwnerDep, SettingsDep
from api.errors import error_responses
from service.settings import signing_key
from service.webhooks import owner_secret

router = APIRouter(prefix="/v1/webhook-secret", tags=["jobs"], responses=error_responses(401, 503))


class WebhookSecret(BaseModel):
    key: str = Field(description="whsec_...: verify `webhook-signature` with HMAC-SHA256 over id.timestamp.body")


@router.get("", response_model=WebhookSecret)
def get_webhook_secret(owner: OwnerDep, settings: SettingsDep) -> WebhookSecret:
    return WebhookSecret(key=owner_secret(signing_key(settings), owner))
