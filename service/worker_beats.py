"""Worker heartbeats in the database (`WorkerBeat` rows), so processes that cannot see the workers
(the API, on another machine or beside an embedded worker) know whether any is alive and idle.

- `/readyz` answers 503 while no worker has beaten within the lease: jobs sent now would wait.
- The reaper (service.queue.reap_stale) sends a queued job again only once a worker has sat idle
  for a whole lease beside it: a live idle worker would have taken the job, so its message was lost.
- `fluidnexus serve` kills and restarts its embedded worker once its row stops moving for
  `worker_unresponsive_seconds` (`BeatWatch`): a frozen worker is replaced like a dead one.

One row per Celery main process (`host:pid`), written by a thread in each pool child every
quarter lease, but only while the main process itself keeps time (`MainClock`): a frozen main
process (SIGSTOP, a hung consumer loop) takes no task, and its pool child, which beat on, kept
it "alive" for ever (issue 49: a job queued 5 min+, `/readyz` "worker ok", 22 broker messages
from the reaper's resends). A stopped or restarted worker's row is removed (`forget`) or simply
goes stale.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session, sessionmaker

from service.database import session_scope
from service.models import WorkerBeat, utcnow

log = logging.getLogger(__name__)


class MainClock:
    """When the Celery main process last kept time, readable by its pool children: a double in
    shared memory, made in the main process before its pool forks (children inherit the mapping),
    set by a timer of the main process (`tick`, worker.tasks.MainTick) and read by each child's
    beacon (`age`). CLOCK_MONOTONIC is one clock for every process of the machine."""

    def __init__(self) -> None:
        import multiprocessing

        self._last = multiprocessing.RawValue("d", time.monotonic())

    def tick(self) -> None:
        self._last.value = time.monotonic()

    def age(self) -> float:
        """Seconds since the main process last ticked."""
        return time.monotonic() - self._last.value


def worker_name(pid: int) -> str:
    """The row name of the Celery main process `pid` on this host (a pool child passes its parent's)."""
    return f"{os.uname().nodename}:{pid}"


class WorkerBeacon:
    """Beats for one worker from a daemon thread; `working()` marks the time a job runs. It beats
    only while `alive()` says the worker's main process answers (`MainClock`); otherwise the row
    goes stale, as a dead worker's does, and its supervisor replaces it."""

    def __init__(self, sessions: sessionmaker[Session], name: str, period_s: float,
                 alive: Callable[[], bool] = lambda: True) -> None:
        self.sessions, self.name, self.period_s, self.alive = sessions, name, period_s, alive
        self._idle_since: datetime | None = utcnow()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat_forever, name="worker-beat", daemon=True)

    def start(self) -> None:
        self._thread.start()

    @contextmanager
    def working(self) -> Iterator[None]:
        self._idle_since = None
        try:
            yield
        finally:
            self._idle_since = utcnow()

    def beat(self) -> None:
        with session_scope(self.sessions) as session:
            row = session.get(WorkerBeat, self.name) or WorkerBeat(name=self.name)
            row.heartbeat_at, row.idle_since = utcnow(), self._idle_since
            session.add(row)

    def stop(self) -> None:
        """Stop beating and remove the row: a worker shutting down is not there any more."""
        self._stop.set()
        forget(self.sessions, self.name)

    def _beat_forever(self) -> None:
        silent = False
        while not self._stop.is_set():
            if not self.alive():
                if not silent:
                    log.warning("worker %s: its main process stopped keeping time; no heartbeat until it does", self.name)
                silent = True
            else:
                silent = False
                try:
                    self.beat()
                except Exception:  # database unreachable: keep trying; readers see the row go stale
                    log.warning("worker heartbeat failed", exc_info=True)
            self._stop.wait(self.period_s)


def forget(sessions: sessionmaker[Session], name: str) -> None:
    """Remove a worker's row (it stopped, or its supervisor saw it die)."""
    with session_scope(sessions) as session:
        session.execute(delete(WorkerBeat).where(WorkerBeat.name == name))


def live_workers(session: Session, lease_seconds: float) -> int:
    """Workers that beat within the lease."""
    cutoff = utcnow() - timedelta(seconds=lease_seconds)
    return session.scalar(select(func.count()).select_from(WorkerBeat).where(WorkerBeat.heartbeat_at >= cutoff)) or 0


def idle_for_a_lease(session: Session, lease_seconds: float) -> bool:
    """True when some live worker has run nothing for at least the lease."""
    cutoff = utcnow() - timedelta(seconds=lease_seconds)
    query = select(func.count()).select_from(WorkerBeat).where(
        WorkerBeat.heartbeat_at >= cutoff, WorkerBeat.idle_since <= cutoff
    )
    return bool(session.scalar(query))


def last_beat(session: Session, name: str) -> datetime | None:
    """When the worker `name` last beat (None: it has not yet, or its row was removed)."""
    return session.scalar(select(WorkerBeat.heartbeat_at).where(WorkerBeat.name == name))


@dataclass
class BeatWatch:
    """Tells when one worker stopped responding: its heartbeat has not moved for `timeout_s`
    seconds of the watcher's own clock (`now`, monotonic), over reads that all succeeded.

    Why this shape: a worker whose process is alive but frozen (SIGSTOP, a hung driver call, a
    deadlock) never exits, so waiting on the process finds nothing; its heartbeat thread stops
    with it. The watcher compares the beat with the last one it read rather than with the wall
    clock, so a database that was down (the worker could not write, the watcher could not read:
    `unreadable`) or a clock step never gets a healthy worker killed, and a worker still booting
    (no beat yet: importing torch can take a while) is not judged at all."""

    timeout_s: float
    _beat: datetime | None = None
    _since: float | None = None  # when the watcher first read the current beat

    def unresponsive(self, beat: datetime | None, now: float) -> bool:
        """Record the beat read at `now`; True once it has not moved for `timeout_s`."""
        if beat is None or beat != self._beat or self._since is None:
            self._beat, self._since = beat, None if beat is None else now
            return False
        return now - self._since >= self.timeout_s

    def unreadable(self) -> None:
        """The beat could not be read: start over, so an outage counts for nothing."""
        self._beat, self._since = None, None
