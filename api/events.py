"""Server-Sent Events of one loop: ``state`` events (the loop's status) and ``sample`` events.

A ``sample`` is an experiment sample while the loop tunes (t, time, PV, SP,
MV, relay, ...) and a monitor reading while it is idle (time, PV, SP, MV,
mode); docs/daemon.md lists the fields. Non-finite numbers are sent as null.

The stream starts with the current state and a ``replay`` event: the trend
the daemon keeps (the running or last session's samples from its start, then
the monitor's; :class:`~autotuner.service.trend.Trend`), so a page opened
mid-tune draws it from the start. Both are taken when the client subscribes,
so the events that follow continue them without a gap or a repeat. A comment
line every ``KEEPALIVE`` seconds keeps proxies from closing an idle stream.
It ends when the daemon stops (after every loop is handed back, with a last
``state``), so the server's wait for open connections never holds up a
shutdown.

:func:`overview` is the stream of every loop at once (``GET /events``, the
operator page's overview): a ``state`` event per loop first, then each
loop's ``state`` events and, instead of every sample, ``live`` events — the
loop's newest sample with its ``loop`` id, at most one per loop every
``LIVE_PERIOD`` seconds — so one connection serves any number of loops
(a browser opens at most 6 per server over HTTP/1.1).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from collections.abc import AsyncIterator
from typing import Any

from autotuner.service.daemon import LoopManager

# Seconds between keep-alive comments on an idle stream.
KEEPALIVE = 15.0
# Wall seconds between two ``live`` events of one loop on the overview stream (the newest sample is sent, the
# ones between are dropped: an overview row shows the value now, not the trend).
LIVE_PERIOD = 0.5
# Events buffered for one overview client; past that the oldest go (a slow client never delays the sampling).
OVERVIEW_QUEUE = 2000


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def frame(event: str, data: dict[str, Any]) -> str:
    """One SSE frame."""
    return f"event: {event}\ndata: {json.dumps(_finite(data), allow_nan=False)}\n\n"


async def stream(manager: LoopManager, loop_id: str) -> AsyncIterator[str]:
    """The loop's events until the client goes away or the daemon stops."""
    queue = manager.subscribe(loop_id)
    state, replay = manager.get(loop_id).as_json(), manager.replay(loop_id)  # no await between: no gap, no repeat
    try:
        yield frame("state", state)
        yield frame("replay", replay)
        while not manager.streams_closed or not queue.empty():
            try:
                event = await asyncio.wait_for(queue.get(), KEEPALIVE)
            except TimeoutError:
                yield ": keep-alive\n\n"
                continue
            if event["event"] == "end":
                return
            yield frame(event["event"], event["data"])
    finally:
        manager.unsubscribe(loop_id, queue)


async def overview(manager: LoopManager) -> AsyncIterator[str]:
    """Every loop's ``state`` events and its ``live`` values (throttled samples), until the client goes away or
    the daemon stops (each loop's stream ended)."""
    merged: asyncio.Queue[tuple[str, dict[str, Any]]] = asyncio.Queue(OVERVIEW_QUEUE)

    async def forward(loop_id: str, queue: asyncio.Queue[dict[str, Any]]) -> None:
        while True:
            event = await queue.get()
            if merged.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    merged.get_nowait()
            merged.put_nowait((loop_id, event))

    queues = {loop_id: manager.subscribe(loop_id) for loop_id in manager.loops}
    states = [loop.as_json() for loop in manager.loops.values()]  # no await since subscribing: no gap, no repeat
    forwarders = [asyncio.create_task(forward(i, q)) for i, q in queues.items()]
    held: dict[str, dict[str, Any]] = {}  # the newest sample of a loop not sent yet
    sent: dict[str, float] = {}  # when a loop's last live event went (monotonic seconds)
    ended: set[str] = set()
    try:
        for state in states:
            yield frame("state", state)
        while len(ended) < len(queues):
            if manager.streams_closed and merged.empty() and all(q.empty() for q in queues.values()):
                return  # everything the daemon sent before it stopped is out (or this client came after it)
            now = time.monotonic()
            for loop_id in [i for i in held if now >= sent.get(i, -math.inf) + LIVE_PERIOD]:
                sent[loop_id] = now
                yield frame("live", {"loop": loop_id, **held.pop(loop_id)})
            wait = min((sent[i] + LIVE_PERIOD - now for i in held), default=KEEPALIVE)
            try:
                loop_id, event = await asyncio.wait_for(merged.get(), max(wait, 0.0))
            except TimeoutError:
                if not held:
                    yield ": keep-alive\n\n"
                continue
            if event["event"] == "end":
                ended.add(loop_id)
                held.pop(loop_id, None)
            elif event["event"] == "sample":
                held[loop_id] = event["data"]
            else:
                held.pop(loop_id, None)  # a state carries the live values too: no older sample after it
                yield frame(event["event"], event["data"])
    finally:
        for task in forwarders:
            task.cancel()
        for loop_id, queue in queues.items():
            manager.unsubscribe(loop_id, queue)
