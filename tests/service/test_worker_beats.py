"""When a worker stopped responding (service.worker_beats.BeatWatch, what `fluidnexus serve`'s
supervisor kills and replaces a worker by), on a fake clock: a heartbeat that has not moved for
the timeout over successful reads; never a worker still booting, nor one whose database was
down; and `last_beat` reading the row a worker's beacon writes."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

from service.database import make_engine, make_sessionmaker, migrate, session_scope
from service.models import utcnow
from service.worker_beats import BeatWatch, WorkerBeacon, forget, last_beat
from tests.support.service import sqlite_url

TIMEOUT = 60.0


def test_a_heartbeat_that_stops_moving_for_the_timeout_is_unresponsive() -> None:
    watch, beat = BeatWatch(TIMEOUT), utcnow()
    assert not watch.unresponsive(beat, now=0.0)
    assert not watch.unresponsive(beat, now=59.0)
    assert watch.unresponsive(beat, now=60.0)


def test_a_moving_heartbeat_starts_the_count_again() -> None:
    watch, beat = BeatWatch(TIMEOUT), utcnow()
    for tick in range(20):  # beats every 4 s for 80 s: never unresponsive
        assert not watch.unresponsive(beat + timedelta(seconds=4 * tick), now=4.0 * tick)
    assert not watch.unresponsive(beat + timedelta(seconds=76), now=130.0)  # last read at 76: 54 s unchanged
    assert watch.unresponsive(beat + timedelta(seconds=76), now=136.0)


def test_a_worker_that_has_not_beaten_yet_is_never_judged() -> None:
    watch = BeatWatch(TIMEOUT)
    assert not any(watch.unresponsive(None, now=float(t)) for t in range(0, 600, 10))  # booting (importing torch)


def test_a_database_outage_counts_for_nothing() -> None:
    """The worker could not write its beat, nor the watcher read it: once the database is back the
    timeout starts from the first read, so a worker that beats again within it is kept."""
    watch, beat = BeatWatch(TIMEOUT), utcnow()
    assert not watch.unresponsive(beat, now=0.0)
    watch.unreadable()  # from 10 s to 100 s
    assert not watch.unresponsive(beat, now=100.0)  # the same stale beat, read again: counted from now
    assert not watch.unresponsive(beat + timedelta(seconds=104), now=104.0)
    assert not watch.unresponsive(beat + timedelta(seconds=104), now=163.0)
    assert watch.unresponsive(beat + timedelta(seconds=104), now=164.0)


def test_last_beat_reads_the_workers_row(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path)
    migrate(url)
    engine = make_engine(url)
    sessions = make_sessionmaker(engine)
    beacon = WorkerBeacon(sessions, "host:42", period_s=60)
    with session_scope(sessions) as session:
        assert last_beat(session, "host:42") is None
    beacon.beat()
    with session_scope(sessions) as session:
        beat = last_beat(session, "host:42")
        assert beat is not None and abs((utcnow() - beat).total_seconds()) < 60
        assert last_beat(session, "host:43") is None
    forget(sessions, "host:42")
    with session_scope(sessions) as session:
        assert last_beat(session, "host:42") is None
    engine.dispose()
