"""A replica follows the shared catalog database: it applies every change, in order, as it commits.

``ChangeFollower`` runs one thread per server process with a connection of its own that
LISTENs on the store's channel (``service.catalog_store.pg_store.CHANNEL``). Every write notifies it at
commit with its change number, so a replica learns of another replica's add within a round
trip; it then calls ``sync`` (the catalog writer's: read the changes after the last one it
applied, in one consistent read, and publish the next snapshot). Notifications are only a
wake-up call: what is applied always comes from the change log, so one lost (the connection
dropped just then) costs nothing but time, and every ``poll_seconds`` the follower asks the
database anyway (the fallback).

When the database cannot be reached the follower says so (``up`` false, ``last_error``), the
replica keeps serving its last snapshot, and the follower reconnects every ``retry_seconds``;
once it is back it catches up from its last applied change before it listens again, so a
replica that was cut off, or started late, ends with every change.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import psycopg

from service.catalog_store.pg_store import CHANNEL
from service.catalog_store.store import StoreError

log = logging.getLogger(__name__)

# Longest wait for a notification before the follower looks at its stop flag and poll timer.
TICK_SECONDS = 0.5


class ChangeFollower:
    """Applies the database's changes to this replica (see the module doc).

    Args:
        connect: opens the LISTEN connection (autocommit).
        last_seq: the database's latest change number.
        sync: brings the replica's snapshot up to the database's latest change.
        applied: the change the replica's snapshot includes.
        poll_seconds: ask the database at least this often (0: notifications alone).
        retry_seconds: wait between reconnection attempts.
    """

    def __init__(self, connect: Callable[[], psycopg.Connection[Any]], last_seq: Callable[[], int],
                 sync: Callable[[], bool], applied: Callable[[], int], poll_seconds: float,
                 retry_seconds: float = 1.0):
        self._connect = connect
        self._last_seq = last_seq
        self._sync = sync
        self._applied = applied
        self.poll_seconds = poll_seconds
        self.retry_seconds = retry_seconds
        self.database_seq = 0          # the latest change number this replica has heard of
        self.up = False
        self.last_error: str | None = None
        self._behind_since: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="catalog-follow", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    # ------------------------------------------------------------------ state
    def heard(self, seq: int) -> None:
        """Note that change ``seq`` exists (a notification, an answer of the database, an own write)."""
        if seq > self.database_seq:
            self.database_seq = seq
        self._update_lag()

    def _update_lag(self) -> None:
        if self._applied() >= self.database_seq:
            self._behind_since = None
        elif self._behind_since is None:
            self._behind_since = time.monotonic()

    @property
    def lost(self) -> bool:
        """True once a round trip of the follower's own connection failed, until it reconnects
        (False while it is still making its first connection at start)."""
        return not self.up and self.last_error is not None

    @property
    def lag_changes(self) -> int:
        return max(0, self.database_seq - self._applied())

    @property
    def lag_seconds(self) -> float:
        """How long the replica has known of a change it has not applied yet (0: up to date)."""
        self._update_lag()
        return 0.0 if self._behind_since is None else time.monotonic() - self._behind_since

    # ------------------------------------------------------------------ the thread
    def _catch_up(self) -> None:
        self.heard(self._last_seq())
        self._sync()
        self._update_lag()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                with self._connect() as conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    self._catch_up()  # what committed while this replica was away or starting
                    if not self.up:
                        log.info("following the catalog database from change %d", self._applied())
                    self.up, self.last_error = True, None
                    self._listen(conn)
            except (psycopg.Error, StoreError) as exc:
                if self.up or self.last_error is None:
                    log.warning("catalog follower: %s; serving change %d until the database is back",
                                str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__,
                                self._applied())
                self.up = False
                self.last_error = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                self._stop.wait(self.retry_seconds)
            except Exception:  # keep following: one failed snapshot must not stop later ones
                log.exception("catalog follower: applying changes failed")
                self._stop.wait(self.retry_seconds)

    def _listen(self, conn: psycopg.Connection[Any]) -> None:
        last_poll = time.monotonic()
        while not self._stop.is_set():
            woken = False
            for note in conn.notifies(timeout=TICK_SECONDS, stop_after=1):
                woken = True
                with contextlib.suppress(ValueError):  # not ours: a wake-up all the same
                    self.heard(int(note.payload))
            polled = self.poll_seconds > 0 and time.monotonic() - last_poll >= self.poll_seconds
            if polled:
                self._catch_up()
                last_poll = time.monotonic()
            elif woken and self.database_seq > self._applied():
                self._sync()
                self._update_lag()
            else:
                conn.execute("SELECT 1")  # the connection is alive (a stopped database is noticed here)
