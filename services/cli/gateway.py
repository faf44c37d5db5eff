"""``thermofield gateway``: the device gateway process (devices, health and capture over HTTP)."""

from __future__ import annotations

import argparse

from services.settings import Settings

_CAMERAS = ("simulated", "oak", "genicam")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "gateway",
        description="Own the station's devices and serve GET /healthz, GET /v1/devices, GET /v1/sequence and "
                    "POST /v1/captures. Configured by THERMOFIELD_* environment variables (see docs/devices.md); "
                    "the options below override them.",
    )
    parser.add_argument("--driver", choices=_CAMERAS,
                        help="every device whose own driver is not chosen: the simulated virtual rig, OAK cameras "
                             "and a display projector, or GenICam cameras and a display projector (default "
                             "THERMOFIELD_GATEWAY_DRIVER, else simulated)")
    parser.add_argument("--camera-driver", choices=_CAMERAS, help="the camera's driver (overrides --driver)")
    parser.add_argument("--thermal-driver", choices=_CAMERAS, help="the thermal camera's driver (overrides --driver)")
    parser.add_argument("--projector-driver", choices=("simulated", "display"),
                        help="the projector's driver (overrides --driver)")
    parser.add_argument("--host", help="address to bind (default THERMOFIELD_GATEWAY_HOST, else 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port to listen on (default THERMOFIELD_GATEWAY_PORT, else 8001)")
    parser.set_defaults(handler=_run)


def settings_of(args: argparse.Namespace) -> Settings:
    """The settings of the environment with the command line's options over them. ``--driver`` stands for the
    driver of every device whose own is not chosen (``--camera-driver`` or THERMOFIELD_CAMERA_DRIVER, and so on):
    the embedded service starts its gateway with ``--driver simulated``, and a camera chosen in the environment
    still joins it."""
    overrides = {"gateway_driver": args.driver, "gateway_host": args.host, "gateway_port": args.port,
                 "camera_driver": args.camera_driver, "thermal_driver": args.thermal_driver,
                 "projector_driver": args.projector_driver}
    return Settings(**{name: value for name, value in overrides.items() if value is not None})


def _run(args: argparse.Namespace) -> int:
    from api.server import HttpLimits, serve
    from device_gateway.service import create_gateway

    settings = settings_of(args)
    app = create_gateway(settings)
    drivers = settings.station_drivers
    print(f"thermofield gateway (camera {drivers.camera}, thermal {drivers.thermal}, projector {drivers.projector}) "
          f"on http://{settings.gateway_host}:{settings.gateway_port}", flush=True)
    serve(app, settings.gateway_host, settings.gateway_port, HttpLimits.of(settings), log_level="warning")
    return 0
