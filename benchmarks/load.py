"""A small HTTP/1.1 keep-alive load generator (asyncio, raw sockets), run as its own process.

    python benchmarks/load.py --url http://127.0.0.1:8000/v1/jobs/ID --header "Authorization: Bearer KEY" \
        --connections 16 --seconds 10

Prints one JSON line: requests, errors, seconds, requests_per_s, p50_ms, p99_ms. Written here
because no HTTP load tool (wrk, hey, ab) is installed on the machine; raw sockets keep the
client's own cost far below the server's, so the server is what is measured.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from urllib.parse import urlsplit

import numpy as np


async def _connection(host: str, port: int, request: bytes, deadline: float, latencies: list[float],
                      errors: list[int]) -> None:
    reader, writer = await asyncio.open_connection(host, port)
    try:
        while time.perf_counter() < deadline:
            start = time.perf_counter()
            writer.write(request)
            status_line = await reader.readline()
            length = 0
            while (line := await reader.readline()) not in (b"\r\n", b""):
                name, _, value = line.partition(b":")
                if name.strip().lower() == b"content-length":
                    length = int(value)
            await reader.readexactly(length)
            latencies.append(time.perf_counter() - start)
            if not status_line.startswith(b"HTTP/1.1 200"):
                errors.append(1)
    finally:
        writer.close()


async def run_load(url: str, headers: list[str], connections: int, seconds: float) -> dict:
    parts = urlsplit(url)
    path = parts.path + (f"?{parts.query}" if parts.query else "")
    lines = [f"GET {path} HTTP/1.1", f"Host: {parts.netloc}", *headers, "", ""]
    request = "\r\n".join(lines).encode()
    latencies: list[float] = []
    errors: list[int] = []
    start = time.perf_counter()
    deadline = start + seconds
    await asyncio.gather(*(_connection(parts.hostname, parts.port, request, deadline, latencies, errors)
                           for _ in range(connections)))
    elapsed = time.perf_counter() - start
    milliseconds = np.asarray(latencies) * 1000
    return {"requests": len(latencies), "errors": len(errors), "seconds": round(elapsed, 3),
            "requests_per_s": round(len(latencies) / elapsed, 1),
            "p50_ms": round(float(np.percentile(milliseconds, 50)), 2),
            "p99_ms": round(float(np.percentile(milliseconds, 99)), 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", required=True)
    parser.add_argument("--header", action="append", default=[])
    parser.add_argument("--connections", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    print(json.dumps(asyncio.run(run_load(args.url, args.header, args.connections, args.seconds))))


if __name__ == "__main__":
    main()
