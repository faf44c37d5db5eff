"""The thermofield HTTP API (FastAPI, mounted under ``/v1``)."""
