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


def test_a_pool_child_beats_only_while_its_main_process_keeps_time(tmp_path: Path) -> None:
    """Issue 49 item 2: the beacon thread runs in the pool child, which beat on while its Celery
    main process was frozen. The main's clock is shared memory a forked child reads."""
    import multiprocessing
    import time

    from service.worker_beats import MainClock

    url = sqlite_url(tmp_path)
    migrate(url)
    engine = make_engine(url)
    sessions = make_sessionmaker(engine)
    clock = MainClock()
    child_saw = multiprocessing.get_context("fork").Queue()
    clock.tick()
    child = multiprocessing.get_context("fork").Process(target=lambda: child_saw.put(clock.age()))
    time.sleep(0.3)
    child.start()
    child.join(10)
    assert 0.3 <= child_saw.get(timeout=5) < 5  # the child reads the tick its parent made before

    beacon = WorkerBeacon(sessions, "host:7", period_s=0.05, alive=lambda: clock.age() < 0.2)
    beacon.start()
    time.sleep(0.5)  # the clock has not ticked for 0.8 s: silent
    with session_scope(sessions) as session:
        assert last_beat(session, "host:7") is None
    clock.tick()
    deadline = time.monotonic() + 5
    while last_beat_of(sessions, "host:7") is None and time.monotonic() < deadline:
        clock.tick()
        time.sleep(0.05)
    assert last_beat_of(sessions, "host:7") is not None  # beating again once the main keeps time
    beacon.stop()
    engine.dispose()


def last_beat_of(sessions, name: str):  # type: ignore[no-untyped-def]
    with session_scope(sessions) as session:
        return last_beat(session, name)
