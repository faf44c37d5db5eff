"""Whether the ports a service command is about to bind are free, checked before anything starts."""

from __future__ import annotations

import socket
from dataclasses import dataclass

from services.errors import InputError


@dataclass(frozen=True)
class Port:
    """One port a command binds: its address, number, what listens there and the option that sets it."""

    host: str
    port: int
    what: str
    option: str


def _in_use(host: str, port: int) -> bool:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        # As uvicorn and gRPC do: a port left in TIME_WAIT by an earlier run is free, one with a listener is not.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError:
            return True
    return False


def require_free(ports: list[Port]) -> None:
    """Raise an ``InputError`` naming the first port another program listens on (port 0 means any free port)."""
    for port in ports:
        if port.port and _in_use(port.host, port.port):
            raise InputError(f"port {port.port} on {port.host} ({port.what}) is in use by another program, perhaps "
                             f"another thermofield; stop it or choose another port with {port.option}")
