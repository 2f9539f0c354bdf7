"""A loop's live events: its subscribers' queues and the trend kept in memory.

Live events go to subscribers (the API's Server-Sent Events) through bounded
queues; a slow subscriber loses the oldest events, it never delays anything
else. Each event is ``{"event": "sample"|"state"|"end", "data": {...}}``.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

from autotuner.service.trend import Trend

# Events kept per subscriber before the oldest are dropped.
QUEUE_EVENTS = 1000


class LoopEvents:
    """The event channel of one loop: its subscribers and its trend (the samples, for a page opened later)."""

    def __init__(self) -> None:
        self.subscribers: set[asyncio.Queue[dict[str, Any]]] = set()
        self.trend = Trend()

    def subscribe(self) -> asyncio.Queue[dict[str, Any]]:
        """A queue receiving the loop's events from now on."""
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue(QUEUE_EVENTS)
        self.subscribers.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue[dict[str, Any]]) -> None:
        """Stop sending events to ``queue``."""
        self.subscribers.discard(queue)

    def publish(self, event: str, data: dict[str, Any]) -> None:
        """Send ``event`` to every subscriber (a full queue loses its oldest event); a sample joins the trend."""
        if event == "sample":
            self.trend.add(data)
        item = {"event": event, "data": data}
        for queue in self.subscribers:
            if queue.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    queue.get_nowait()
            queue.put_nowait(item)
