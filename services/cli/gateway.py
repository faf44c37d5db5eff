"""``thermofield gateway``: the device gateway process (devices, health and capture over HTTP)."""

from __future__ import annotations

import argparse

from services.settings import Settings


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "gateway",
        description="Own the station's devices and serve GET /healthz, GET /v1/devices, GET /v1/sequence and "
                    "POST /v1/captures. Configured by THERMOFIELD_* environment variables (see docs/devices.md); "
                    "the options below override them.",
    )
    parser.add_argument("--driver", choices=("simulated", "oak"),
                        help="simulated virtual rig, or OAK cameras and a display projector "
                             "(default THERMOFIELD_GATEWAY_DRIVER, else simulated)")
    parser.add_argument("--host", help="address to bind (default THERMOFIELD_GATEWAY_HOST, else 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port to listen on (default THERMOFIELD_GATEWAY_PORT, else 8001)")
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from api.server import HttpLimits, serve
    from device_gateway.service import create_gateway

    overrides = {"gateway_driver": args.driver, "gateway_host": args.host, "gateway_port": args.port}
    settings = Settings(**{name: value for name, value in overrides.items() if value is not None})
    app = create_gateway(settings)
    print(f"thermofield gateway ({settings.gateway_driver} devices) on "
          f"http://{settings.gateway_host}:{settings.gateway_port}", flush=True)
    serve(app, settings.gateway_host, settings.gateway_port, HttpLimits.of(settings), log_level="warning")
    return 0
