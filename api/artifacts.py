"""The artifact store as the routes read it: a blob that a row names but the store lacks is a 404 problem."""

from __future__ import annotations

import logging
from pathlib import Path

from api.problems import Problem
from services.storage.artifacts import ArtifactStore

logger = logging.getLogger(__name__)


def stored_path(store: ArtifactStore, digest: str, owner: str) -> Path:
    """The file of ``digest``, which ``owner`` (e.g. ``"scan 1f2e"``) names.

    Raises
    ------
    Problem
        404 ``artifact-missing`` when the store has no such blob (removed by hand, or a store restored from an
        older backup than the database): the client cannot have it, and the operator is told in the log.
    """
    try:
        return store.path(digest)
    except KeyError:
        logger.error("artifact %s of %s is missing from the store at %s", digest, owner, store.root)
        raise Problem(404, "artifact-missing", f"The artifact {digest} of {owner} is missing from the store; "
                                               "ask the station's operator.") from None


def stored_bytes(store: ArtifactStore, digest: str, owner: str) -> bytes:
    """The content of ``digest``, which ``owner`` names; 404 ``artifact-missing`` as :func:`stored_path`."""
    return stored_path(store, digest, owner).read_bytes()
