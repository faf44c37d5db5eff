"""Rate limits per API key, and of failed authentications per client address: a token bucket per key (or
address) in each API process (429 + ``Retry-After`` beyond it).

Each key may make ``rate`` requests per second on average and ``burst`` at once. The
buckets live in the API process (no shared store is needed for a limit whose purpose
is to stop one runaway client from starving the others), so with N API replicas
behind a balancer a key gets up to N times the rate.
"""

from __future__ import annotations

import math
import threading
import time


_MAX_BUCKETS = 100_000  # addresses are many where keys are few


class RateLimiter:
    """Token buckets by key id; ``rate`` 0 turns the limit off."""

    def __init__(self, rate: float, burst: int) -> None:
        self.rate, self.burst = rate, max(burst, 1)
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def wait_seconds(self, key_id: str) -> int:
        """Take one token for ``key_id``: 0 when the request may go ahead, else the whole seconds to wait."""
        if self.rate <= 0:
            return 0
        now = time.monotonic()
        with self._lock:
            if len(self._buckets) > _MAX_BUCKETS:  # full buckets only: forgetting them changes nothing
                self._buckets = {key: (tokens, then) for key, (tokens, then) in self._buckets.items()
                                 if tokens + (now - then) * self.rate < self.burst}
            tokens, then = self._buckets.get(key_id, (float(self.burst), now))
            tokens = min(float(self.burst), tokens + (now - then) * self.rate)
            if tokens >= 1.0:
                self._buckets[key_id] = (tokens - 1.0, now)
                return 0
            self._buckets[key_id] = (tokens, now)
            return max(1, math.ceil((1.0 - tokens) / self.rate))

    def refund(self, key_id: str) -> None:
        """Give back the token a request took (it turned out not to count: a failure limit's good key)."""
        with self._lock:
            if key_id in self._buckets:
                tokens, then = self._buckets[key_id]
                self._buckets[key_id] = (min(float(self.burst), tokens + 1.0), then)
