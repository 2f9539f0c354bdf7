"""A process that keeps time has its start's objects out of the garbage collector's full walks (heap.py)."""

from __future__ import annotations

import gc
import subprocess
import sys

from fastapi.testclient import TestClient

from api.app import create_app
from autotuner.service import heap
from test_api import CONFIG, OPERATOR


def test_settle_takes_the_held_objects_out_of_the_full_collections_and_release_gives_them_back():
    held = [[k] for k in range(20_000)]  # containers a full collection walks
    gc.collect()
    before = len(gc.get_objects(generation=2))
    try:
        frozen = heap.settle()
        assert frozen >= before > 20_000
        assert len(gc.get_objects(generation=2)) < 0.01 * before  # what a full collection walks now
    finally:
        heap.release()
    assert gc.get_freeze_count() == 0
    assert len(gc.get_objects(generation=2)) >= before
    del held


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
