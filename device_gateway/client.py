"""Python client of the gateway's HTTP API, used by the workers."""

from __future__ import annotations

from functools import cache
from typing import Any

import httpx

from device_gateway.devices import DeviceError
from device_gateway.station import BoardViews, Capture, StationCapture
from device_gateway.transfer import (BOARD_VIEWS_MEDIA_TYPE, MEDIA_TYPE, STATION_MEDIA_TYPE, decode_board_views,
                                     decode_capture, decode_station_capture)
from services.formats.sequence import Sequence


class GatewayError(DeviceError):
    """The gateway could not be reached or refused the request; the message carries its problem detail."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class GatewayClient:
    """Talks to one gateway at ``base_url`` (e.g. ``http://127.0.0.1:8001``).

    ``timeout_s`` bounds each request; a capture of a few dozen patterns with a real
    projector takes seconds, so it is generous by default.
    """

    def __init__(self, base_url: str, timeout_s: float = 60.0) -> None:
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(base_url=self.base_url, timeout=timeout_s, verify=_tls_context())

    def __enter__(self) -> GatewayClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def health(self) -> dict[str, Any]:
        """``{"status": "ok" | "degraded", "devices": {name: open}}`` (a degraded gateway is not an error here)."""
        response = self._request("GET", "/healthz", accept=(200, 503))
        return response.json()

    def devices(self) -> list[dict[str, Any]]:
        return self._request("GET", "/v1/devices").json()

    def sequence(self) -> Sequence:
        return Sequence.model_validate(self._request("GET", "/v1/sequence").json())

    def capture(self, thermal_frames: int = 1, exposure: str = "fixed") -> Capture | StationCapture:
        """Run one capture on the station (``exposure``: fixed, auto or hdr) and return its frames, thermal
        frames and metadata: a :class:`StationCapture` (every head's frames) from a gateway of several heads."""
        response = self._request("POST", "/v1/captures", json={"thermal_frames": thermal_frames,
                                                               "exposure": exposure})
        if response.headers.get("content-type") == STATION_MEDIA_TYPE:
            return decode_station_capture(response.content)
        if response.headers.get("content-type") != MEDIA_TYPE:
            raise GatewayError(f"gateway {self.base_url} answered {response.headers.get('content-type')!r}, "
                               f"not a capture archive", response.status_code)
        return decode_capture(response.content)

    def board_views(self, board: dict[str, Any], views: int, interval_s: float = 2.0) -> BoardViews:
        """Film a calibration board (a board file's JSON) in ``views`` poses with both cameras."""
        response = self._request("POST", "/v1/board-views",
                                 json={"board": board, "views": views, "interval_s": interval_s})
        if response.headers.get("content-type") != BOARD_VIEWS_MEDIA_TYPE:
            raise GatewayError(f"gateway {self.base_url} answered {response.headers.get('content-type')!r}, "
                               f"not board views", response.status_code)
        return decode_board_views(response.content)

    def _request(self, method: str, path: str, accept: tuple[int, ...] = (200,), **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except (httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError) as error:
            raise GatewayError(f"gateway {self.base_url} stopped answering during {method} {path} (the gateway "
                               f"or a device was lost): {error}") from None
        except httpx.TimeoutException:
            raise GatewayError(f"gateway {self.base_url} did not answer {method} {path} within "
                               f"{self._http.timeout.read} s") from None
        except httpx.HTTPError as error:
            raise GatewayError(f"gateway {self.base_url} unreachable: {error}") from None
        if response.status_code not in accept:
            raise GatewayError(f"gateway {self.base_url}{path}: {response.status_code} {_detail(response)}",
                               response.status_code)
        return response


@cache
def _tls_context():
    """httpx's default TLS context, made once: loading the CA bundle costs 40 ms, every client a worker opens."""
    return httpx.create_ssl_context()


def _detail(response: httpx.Response) -> str:
    try:
        return response.json().get("detail") or response.reason_phrase
    except ValueError:
        return response.reason_phrase
