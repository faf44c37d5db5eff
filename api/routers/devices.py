"""Devices: what the station's gateway reports."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool

from api.deps import ReaderKey, RuntimeDep
from api.problems import Problem, problem_responses

router = APIRouter(prefix="/devices", tags=["devices"])


@router.get("", name="list_devices", responses=problem_responses(502))
async def list_devices(runtime: RuntimeDep, _: ReaderKey) -> list[dict[str, Any]]:
    """The gateway's devices with their driver, size and whether they are open."""
    # imported here: the client's capture decoding brings the station's code, which the API needs nowhere else
    from device_gateway.client import GatewayClient, GatewayError

    def fetch() -> list[dict[str, Any]]:
        with GatewayClient(runtime.settings.gateway_url, timeout_s=5.0) as client:
            return client.devices()

    try:
        return await run_in_threadpool(fetch)
    except GatewayError as error:
        raise Problem(502, "gateway-unavailable", str(error))
