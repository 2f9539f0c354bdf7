"""A process that keeps time has its start's objects out of the garbage collector's full walks (heap.py)."""

from __future__ import annotations

import gc
import subprocess
import sys

from fastapi.testclient import TestClient

from api.app import create_app
from autotuner.service import heap
from test_api import CONFIG, OPERATOR


def _walked(held: list[list[int]]) -> int:
    """How many of ``held`` a full collection walks now."""
    walked = {id(o) for o in gc.get_objects(generation=2)}
    return sum(id(x) in walked for x in held)


def test_settle_takes_the_held_objects_out_of_the_full_collections_and_release_gives_them_back():
    held = [[k] for k in range(20_000)]  # containers a full collection walks
    gc.collect()
    before = len(gc.get_objects(generation=2))
    assert _walked(held) == len(held)
    try:
        frozen = heap.settle()
        assert frozen > len(held) and before > len(held)  # the collection before the freeze may free some garbage
        assert _walked(held) == 0
        assert len(gc.get_objects(generation=2)) < 0.01 * before  # what a full collection walks now
    finally:
        heap.release()
    assert gc.get_freeze_count() == 0
    assert _walked(held) == len(held)


def test_a_daemon_settles_its_heap_once_started_and_releases_it_when_it_stops():
    gc.unfreeze()
    with TestClient(create_app(CONFIG, env_token=OPERATOR)):
        assert gc.get_freeze_count() > 50_000  # the imports, the app, the loops
    assert gc.get_freeze_count() == 0


def test_an_analysis_worker_settles_its_heap_when_it_starts():
    # In a fresh interpreter, as a spawned worker starts: the setup's module brings the engine in with it.
    code = ("import gc; from autotuner.service.daemon.analyses import _worker_setup; _worker_setup(None); "
            "print(gc.get_freeze_count())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert int(out.stdout) > 50_000  # numpy, scipy, the engine
