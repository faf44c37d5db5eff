"""Dramatiq group completion barriers in the service's database.

A Dramatiq group runs a completion callback once every message of the group has been processed
(``dramatiq.middleware.GroupCallbacks``); the count of messages still to finish lives in a rate-limiter
backend that every worker process shares. The service has its database in every process (embedded and
scaled out), so the barrier is a row of ``group_barriers``: created with the group's size, decremented
atomically by each message that finishes (an ``UPDATE ... WHERE value - 1 >= minimum``, one statement),
the last one (whose decrement is refused at 1) enqueuing the callback. Only what a barrier uses is
implemented (``add``, ``decr``, a non-blocking ``wait``); rate limiting is not.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime, timedelta

from dramatiq.rate_limits import RateLimiterBackend
from sqlalchemy import delete, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import GroupBarrier


class DatabaseBarrierBackend(RateLimiterBackend):
    """Barrier counts in the ``group_barriers`` table of ``sessions()`` (a function, so that the worker's runtime
    is built on first use)."""

    def __init__(self, sessions: Callable[[], sessionmaker[Session]]) -> None:
        self._sessions = sessions

    def add(self, key: str, value: int, ttl: int) -> bool:
        now = datetime.now(UTC)
        try:
            with self._sessions().begin() as session:
                session.execute(delete(GroupBarrier).where(GroupBarrier.expires_at < now))
                session.add(GroupBarrier(key=key, value=value, expires_at=now + timedelta(milliseconds=ttl)))
        except IntegrityError:
            return False
        return True

    def decr(self, key: str, amount: int, minimum: int, ttl: int) -> bool:
        with self._sessions().begin() as session:
            changed = session.execute(
                update(GroupBarrier).where(GroupBarrier.key == key, GroupBarrier.value - amount >= minimum,
                                           GroupBarrier.expires_at >= datetime.now(UTC))
                .values(value=GroupBarrier.value - amount)).rowcount
            if not changed:  # the last party: the barrier is cleared and goes
                session.execute(delete(GroupBarrier).where(GroupBarrier.key == key))
        return bool(changed)

    def wait_notify(self, key: str, ttl: int) -> None:
        """Nobody blocks on a group's barrier: nothing to notify."""

    def wait(self, key: str, timeout: int) -> bool:
        raise NotImplementedError("the database barrier does not block; Dramatiq's group callbacks never wait")

    def incr(self, key: str, amount: int, maximum: int, ttl: int) -> bool:
        raise NotImplementedError("the database barrier backend is no rate limiter")

    def incr_and_sum(self, key, keys, amount, maximum, ttl) -> bool:
        raise NotImplementedError("the database barrier backend is no rate limiter")
