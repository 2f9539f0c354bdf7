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
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import AsyncIterator
from typing import Any

from autotuner.service.daemon import LoopManager

# Seconds between keep-alive comments on an idle stream.
KEEPALIVE = 15.0


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
