"""The OPC UA server's security: its application certificate, the client certificates it trusts, and users that
are API keys (user name: any label; password: the key's secret), whose scopes decide which methods they call.
"""

from __future__ import annotations

import contextvars
import logging
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from asyncua.crypto.permission_rules import SimpleRoleRuleset, User, UserRole
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.db.apikeys import SCOPES, secret_digest
from services.db.models import ApiKey
from services.errors import InputError

if TYPE_CHECKING:
    from asyncua import Server

logger = logging.getLogger(__name__)

KEY_CACHE_S = 5.0
"""A revoked key stops working within this time (the HTTP API's cache time)."""

METHOD_SCOPES = {
    # state machine and automatic mode
    "Halt": "operate", "Reset": "operate", "SelectModeAutomatic": "operate", "StartSingleJob": "operate",
    "StartContinuous": "operate", "Stop": "operate", "Abort": "operate",
    # recipes: preparing one selects the station's part type (admin, as POST /v1/part-types/{id}/select)
    "PrepareRecipe": "admin", "UnprepareRecipe": "admin", "GetRecipeListFiltered": "read",
    # configurations: activating one activates a calibration set (admin, as over HTTP)
    "ActivateConfiguration": "admin", "GetConfigurationById": "read", "GetConfigurationList": "read",
    # results
    "GetResultById": "read", "GetResultComponentsById": "read", "GetResultListFiltered": "read",
}
"""The API scope each method needs; a higher scope includes the lower ones."""


@dataclass
class KeyUser(User):
    """An OPC UA session's user: the API key whose secret was its password."""

    key_digest: str = ""
    scopes: tuple[str, ...] = ()


_caller: contextvars.ContextVar[User | None] = contextvars.ContextVar("opcua_caller", default=None)


def caller() -> User | None:
    """The user of the request being served (set by :class:`CallerRuleset` before the server handles it)."""
    return _caller.get()


class CallerRuleset(SimpleRoleRuleset):
    """asyncua's role rules, which also note who sends each request.

    asyncua hands a method's callback no session or user. Each client connection's requests are handled one
    after the other in one task, which checks this ruleset right before handling a request (the call of a
    method's callback included): the user noted here in a context variable is the caller's.
    """

    def check_validity(self, user, action_type_id, body):
        _caller.set(user)
        return super().check_validity(user, action_type_id, body)


class ApiKeyUsers:
    """asyncua's user manager: a user name with an API key's secret as its password (the user name is only
    logged); the key's scopes are re-read every ``KEY_CACHE_S`` so that a revoked key stops working."""

    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self.sessions = sessions
        self._cache: dict[str, tuple[float, tuple[str, ...]]] = {}

    def get_user(self, iserver, username: str | None = None, password: str | bytes | None = None,
                 certificate=None) -> User | None:
        if isinstance(password, bytes):
            password = password.decode("utf-8", "replace")
        if not password:
            return None
        digest = secret_digest(password)
        scopes = self.scopes(digest)
        if scopes is None:
            logger.warning("OPC UA: user %r sent an unknown or revoked API key", username)
            return None
        return KeyUser(role=UserRole.User, name=username, key_digest=digest, scopes=scopes)

    def scopes(self, digest: str) -> tuple[str, ...] | None:
        """The scopes of the unrevoked key with this secret digest, None for none."""
        cached = self._cache.get(digest)
        if cached is not None and cached[0] > time.monotonic():
            return cached[1]
        with self.sessions() as session:
            granted = session.scalar(select(ApiKey.scopes).where(ApiKey.secret_sha256 == digest,
                                                                 ApiKey.revoked_at.is_(None)))
            scopes = None if granted is None else tuple(granted.split())
        if scopes is not None:
            if len(self._cache) > 10_000:
                self._cache.clear()
            self._cache[digest] = (time.monotonic() + KEY_CACHE_S, scopes)
        return scopes

    def may_call(self, user: User | None, method: str) -> bool:
        """Whether ``user``'s key (still) grants the scope ``method`` needs."""
        if not isinstance(user, KeyUser):
            return False
        scopes = self.scopes(user.key_digest)
        needed = SCOPES.index(METHOD_SCOPES[method])
        return scopes is not None and any(SCOPES.index(scope) >= needed for scope in scopes)


def application_uri(station: str) -> str:
    return f"urn:thermofield:{socket.gethostname()}:{station}"


async def load_server_certificate(server: Server, pki_dir: Path, certificate: Path | None,
                                  private_key: Path | None, station: str, host: str) -> Path:
    """Load the operator's certificate and key, or the ones created in ``pki_dir`` on the first start (RSA 2048,
    self-signed, valid one year: renewed when expired or when the host name changes); the certificate's path."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    if (certificate is None) != (private_key is None):
        raise InputError("THERMOFIELD_OPCUA_CERTIFICATE and THERMOFIELD_OPCUA_PRIVATE_KEY go together; set both "
                         "or neither (then the server makes its own)")
    if certificate is None:
        pki_dir.mkdir(parents=True, exist_ok=True)
        (pki_dir / "trusted").mkdir(exist_ok=True)
        certificate, private_key = pki_dir / "server-certificate.der", pki_dir / "server-key.pem"
        await setup_self_signed_certificate(private_key, certificate, application_uri(station), host,
                                            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                                            {"commonName": f"thermofield {station}", "organizationName": "thermofield"})
        private_key.chmod(0o600)
    for path, what in ((certificate, "THERMOFIELD_OPCUA_CERTIFICATE"), (private_key, "THERMOFIELD_OPCUA_PRIVATE_KEY")):
        if not path.is_file():
            raise InputError(f"{what}: {path} is not a file")
    try:
        await server.load_certificate(str(certificate))
        await server.load_private_key(str(private_key))
    except ValueError as error:
        raise InputError(f"{certificate}: not a certificate and private key the OPC UA server can use ({error})") \
            from None
    return certificate


def trusted_clients_validator(trusted_dir: Path):
    """A certificate check for asyncua: a client's certificate must be in ``trusted_dir`` (DER or PEM, or signed
    by a CA certificate there), within its validity and carry the application URI the client claims. The
    directory is re-read on every connection: trusting a client needs no restart."""
    from asyncua.crypto.truststore import TrustStore
    from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

    store = TrustStore([trusted_dir], [])
    validator = CertificateValidator(CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI
                                     | CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.PEER_CLIENT,
                                     store)

    async def validate(certificate, application) -> None:
        trusted_dir.mkdir(parents=True, exist_ok=True)
        await store.load_trust()
        try:
            await validator(certificate, application)
        except Exception:
            logger.warning("OPC UA: refused the certificate of client %r (%s); to trust it, copy it into %s",
                           application.ApplicationUri, certificate.subject.rfc4514_string(), trusted_dir)
            raise

    return validate
