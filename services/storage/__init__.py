"""Content-addressed artifact store for frames, clouds, fields and recordings."""

from services.storage.artifacts import ArtifactStore

__all__ = ["ArtifactStore"]
