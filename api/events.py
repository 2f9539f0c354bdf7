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
(a browser opens at most 6 per server over HTTP/1.1). One reader of every
loop (:class:`Overview`) serves all the overview streams.

Each event is encoded once (:func:`event_frame`), whatever the number of
streams it goes to: a dashboard open on many screens costs the daemon a
queue entry and a socket write per stream, not a JSON encoding.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
from collections.abc import AsyncIterator, Iterator
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


class OpenStreams:
    """How many event streams are open now (the daemon's metrics)."""

    def __init__(self) -> None:
        self.count = 0

    @contextlib.contextmanager
    def one(self) -> Iterator[None]:
        """Counted while the ``with`` block runs."""
        self.count += 1
        try:
            yield
        finally:
            self.count -= 1


async def stream(manager: LoopManager, loop_id: str, open_streams: OpenStreams) -> AsyncIterator[str]:
    """The loop's events until the client goes away or the daemon stops."""
    with open_streams.one():
        async for frame_text in _stream(manager, loop_id):
            yield frame_text


def event_frame(event: dict[str, Any], kind: str = "sse") -> str:
    """The frame of a loop's event (``kind`` "sse": as is; "live:ID": the overview's live event of loop ID),
    encoded once whatever the number of streams it goes to (kept in the event's ``frames``)."""
    frames = event.setdefault("frames", {})
    text = frames.get(kind)
    if text is None:
        if kind == "sse":
            text = frame(event["event"], event["data"])
        else:
            text = frame("live", {"loop": kind.removeprefix("live:"), **event["data"]})
        frames[kind] = text
    return text


async def _stream(manager: LoopManager, loop_id: str) -> AsyncIterator[str]:
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
            yield event_frame(event)
    finally:
        manager.unsubscribe(loop_id, queue)


async def overview(manager: LoopManager, hub: Overview, open_streams: OpenStreams) -> AsyncIterator[str]:
    """Every loop's ``state`` events and its ``live`` values (throttled samples), until the client goes away or
    the daemon stops (each loop's stream ended)."""
    with open_streams.one():
        queue, states = hub.join(manager)  # no await between: no gap, no repeat
        try:
            for state in states:
                yield frame("state", state)
            while True:
                try:
                    text = await asyncio.wait_for(queue.get(), KEEPALIVE)
                except TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                if text is None:
                    return
                yield text
        finally:
            hub.leave(queue)


class Overview:
    """The overview streams' one reader of every loop: each loop's state events at once and its newest sample
    at most every :data:`LIVE_PERIOD` seconds, framed once and handed to every overview client's queue (text;
    None at the end: the daemon stopped). A client that does not read loses the oldest text."""

    def __init__(self) -> None:
        self.clients: set[asyncio.Queue[str | None]] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._ended = False

    def join(self, manager: LoopManager) -> tuple[asyncio.Queue[str | None], list[dict[str, Any]]]:
        """A new client: its queue and every loop's state now (the queue continues them)."""
        if not self._tasks and not self._ended:
            self._start(manager)
        queue: asyncio.Queue[str | None] = asyncio.Queue(OVERVIEW_QUEUE)
        if self._ended:
            queue.put_nowait(None)
        else:
            self.clients.add(queue)
        return queue, [loop.as_json() for loop in manager.loops.values()]

    def leave(self, queue: asyncio.Queue[str | None]) -> None:
        """The client went away."""
        self.clients.discard(queue)

    def _send(self, text: str | None) -> None:
        for queue in self.clients:
            if queue.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    queue.get_nowait()
            queue.put_nowait(text)

    def _start(self, manager: LoopManager) -> None:
        held: dict[str, dict[str, Any]] = {}  # the newest sample of a loop not sent yet
        ended: set[str] = set()

        async def forward(loop_id: str, queue: asyncio.Queue[dict[str, Any]]) -> None:
            try:
                while (event := await queue.get())["event"] != "end":
                    if event["event"] == "sample":
                        held[loop_id] = event
                    else:
                        held.pop(loop_id, None)  # a state carries the live values too: no older sample after it
                        self._send(event_frame(event))
            finally:
                manager.unsubscribe(loop_id, queue)
            held.pop(loop_id, None)
            ended.add(loop_id)
            if len(ended) == len(manager.loops):
                self._ended = True
                self._send(None)

        async def live() -> None:
            while not self._ended:
                await asyncio.sleep(LIVE_PERIOD)
                if held and self.clients:
                    self._send("".join(event_frame(event, f"live:{loop_id}") for loop_id, event in held.items()))
                held.clear()

        # Subscribed now, before the first client's states are taken: nothing between them is lost.
        self._tasks = [asyncio.create_task(forward(loop_id, manager.subscribe(loop_id))) for loop_id in manager.loops]
        self._tasks.append(asyncio.create_task(live()))
