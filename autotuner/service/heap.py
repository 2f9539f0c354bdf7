"""The garbage collector's full collections out of the way of a process that keeps time.

A full (generation 2) collection walks every container object the process
holds, with its event loop stopped. After the imports of numpy, scipy,
pydantic and FastAPI and the app's start that is about 190 000 objects:
measured up to 117 ms per full collection in a daemon's process (2026-12-05,
``samplers: 0``, one TIC-101 tuning), more than the own lateness a fast
loop's experiment tolerates (a tenth of its period). What a process holds once
it has started — modules, classes, the app, the loops' configs — lives as long
as the process; frozen into the permanent generation, the collections no
longer walk it, and a full one walks only what was made since.
"""

from __future__ import annotations

import gc


def settle() -> int:
    """Collect what the start left behind, then take every object the process holds now out of the collector's
    walks (:func:`gc.freeze`); the number of objects so taken out. Call once a process that keeps time has
    started, before its first session."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def release() -> None:
    """Give the objects :func:`settle` took out back to the collector (:func:`gc.unfreeze`): a process that
    stops serving but goes on (a test's process) collects them again."""
    gc.unfreeze()
