"""API keys: create (the secret is shown once), list and revoke; admin scope."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool

from api.deps import AdminKey, SessionDep
from api.problems import Problem, problem_responses
from api.schemas import ApiKeyCreated, ApiKeyOut, ApiKeyRequest
from services.db.apikeys import create_api_key, list_api_keys, revoke_api_key
from services.db.models import ApiKey

router = APIRouter(prefix="/api-keys", tags=["api keys"])


def api_key_out(key: ApiKey) -> ApiKeyOut:
    return ApiKeyOut(api_key_id=key.id, name=key.name, scopes=key.scopes.split(), created_at=key.created_at,
                     revoked_at=key.revoked_at)


@router.post("", name="create_api_key", status_code=201)
def create_key(body: ApiKeyRequest, session: SessionDep, _: AdminKey) -> ApiKeyCreated:
    """A new key with ``scopes``; its secret is in this answer only."""
    key, secret = create_api_key(session, body.name, list(body.scopes))
    session.commit()
    return ApiKeyCreated(**api_key_out(key).model_dump(), secret=secret)


@router.get("", name="list_api_keys")
def list_keys(session: SessionDep, _: AdminKey) -> list[ApiKeyOut]:
    """Every key, newest first, revoked ones included; never a secret."""
    return [api_key_out(key) for key in list_api_keys(session)]


@router.delete("/{api_key_id}", name="revoke_api_key", responses=problem_responses(404))
async def revoke_key(api_key_id: str, request: Request, session: SessionDep, _: AdminKey) -> ApiKeyOut:
    """Revoke a key: it stops working at once on this API process, within 5 s on the others."""

    def revoke() -> ApiKey:
        try:
            key = revoke_api_key(session, api_key_id)
        except KeyError:
            raise Problem(404, "not-found", f"There is no API key {api_key_id!r}.") from None
        session.commit()
        return key

    key = await run_in_threadpool(revoke)
    request.app.state.key_cache.evict(key.id)
    return api_key_out(key)
