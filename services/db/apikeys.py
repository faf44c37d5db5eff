"""API keys: random secrets shown once, stored as SHA-256 digests, with hierarchical scopes.

Scopes are ``read`` (GET), ``operate`` (start scans and jobs) and ``admin`` (manage
calibration sets); each includes the ones before it. A secret has 256 random bits,
so a plain SHA-256 suffices (no password-stretching needed) and lookups stay O(1).
"""

from __future__ import annotations

import hashlib
import secrets
from datetime import UTC, datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from services.db.models import ApiKey

SCOPES = ("read", "operate", "admin")
SECRET_PREFIX = "tf_"


def secret_digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def parse_scopes(scopes: list[str]) -> list[str]:
    """Validate scope names, given as separate words or comma-separated (``read operate``, ``read,operate``,
    ``"read, operate"``); ``ValueError`` names the unknown one."""
    scopes = [scope.strip().lower() for word in scopes for scope in word.replace(",", " ").split()]
    unknown = [scope for scope in scopes if scope not in SCOPES]
    if unknown or not scopes:
        raise ValueError(f"Scopes must be a non-empty subset of {', '.join(SCOPES)}; "
                         f"got {', '.join(scopes) or 'none'}.")
    return sorted(set(scopes), key=SCOPES.index)


def create_api_key(session: Session, name: str, scopes: list[str]) -> tuple[ApiKey, str]:
    """Add a key with ``scopes`` to the session; return the row and the secret (shown once, never stored)."""
    secret = SECRET_PREFIX + secrets.token_urlsafe(32)
    key = ApiKey(name=name, secret_sha256=secret_digest(secret), scopes=" ".join(parse_scopes(scopes)))
    session.add(key)
    session.flush()
    return key, secret


def find_api_key(session: Session, secret: str) -> ApiKey | None:
    """The unrevoked key whose secret is ``secret``."""
    return session.scalar(
        select(ApiKey).where(ApiKey.secret_sha256 == secret_digest(secret), ApiKey.revoked_at.is_(None))
    )


def grants(key: ApiKey, scope: str) -> bool:
    """Whether ``key`` may act with ``scope`` (a higher scope includes the lower ones)."""
    granted = key.scopes.split()
    return any(SCOPES.index(g) >= SCOPES.index(scope) for g in granted)


def list_api_keys(session: Session) -> list[ApiKey]:
    """Every key, newest first, revoked ones included (their ``revoked_at`` is set)."""
    return list(session.scalars(select(ApiKey).order_by(ApiKey.created_at.desc())))


def revoke_api_key(session: Session, key_id: str) -> ApiKey:
    """Revoke the key ``key_id`` (the caller commits); ``KeyError`` if there is none. Revoking twice keeps
    the first time."""
    key = session.get(ApiKey, key_id)
    if key is None:
        raise KeyError(key_id)
    if key.revoked_at is None:
        key.revoked_at = datetime.now(UTC)
    return key
