"""The ground-overhead benchmark's breakdown (`benchmarks.bench_ground_overhead`) on work whose answer is known."""

from __future__ import annotations

import cProfile
import pstats
import time

from benchmarks.bench_ground_overhead import _cameras_in_calling_thread, part_seconds


def _spin(seconds: float) -> None:
    """Burn ``seconds`` of CPU time."""
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def _outer() -> None:
    _spin(0.05)
    _inner()


def _inner() -> None:
    _spin(0.1)


def test_parts_are_the_cumulative_cpu_time_of_the_named_functions() -> None:
    profile = cProfile.Profile(time.process_time)
    profile.enable()
    _outer()
    _inner()
    profile.disable()
    parts = part_seconds(pstats.Stats(profile), {"outer": "_outer", "inner": "_inner", "absent": "_nowhere"})
    assert 0.15 <= parts["outer"] < 0.2  # its own spin and the inner call beneath it
    assert 0.2 <= parts["inner"] < 0.25  # both calls, the one inside _outer included
    assert parts["absent"] == 0.0


def test_the_frame_pool_runs_in_the_calling_thread_and_is_restored() -> None:
    import threading

    from weatheralign.simulate import observe

    pool = observe.ThreadPoolExecutor
    with _cameras_in_calling_thread():
        with observe.ThreadPoolExecutor(max_workers=2) as calls:
            threads = calls.map(lambda _: threading.get_ident(), range(3))
            future = calls.submit(threading.get_ident)
        assert threads == [threading.get_ident()] * 3 and future.result() == threading.get_ident()
    assert observe.ThreadPoolExecutor is pool
