"""asyncua client helpers shared by the OPC UA tests: connecting as a user, raw method calls, reading a loop's
variables, waiting for a condition, and a subscription handler that keeps what it receives."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import Client, ua

from api.opcua.address_space import NAMESPACE


def run(coro: Awaitable[Any], timeout: float = 120.0) -> Any:
    """Run ``coro`` in a new event loop, at most ``timeout`` wall seconds."""
    return asyncio.run(asyncio.wait_for(coro, timeout))


def client(url: str, user: str | None, password: str = "") -> Client:
    """An asyncua client of ``url`` logging in as ``user`` (None: anonymous); connect with ``async with``."""
    c = Client(url, timeout=10)
    if user is not None:
        c.set_user(user)
        c.set_password(password)
    return c


async def call(c: Client, loop_id: str, method: str, *args: Any) -> ua.CallMethodResult:
    """The raw result of a method call (status, outputs) without asyncua's raise on a Bad status; a refusal of
    the whole request (a service fault) still raises."""
    idx = await c.get_namespace_index(NAMESPACE)
    kinds = {str: ua.VariantType.String, float: ua.VariantType.Double, bool: ua.VariantType.Boolean}
    request = ua.CallMethodRequest(ObjectId=ua.NodeId(loop_id, idx), MethodId=ua.NodeId(f"{loop_id}.{method}", idx),
                                   InputArguments=[ua.Variant(a, kinds[type(a)]) for a in args])
    return (await c.uaclient.call([request]))[0]


async def value(c: Client, loop_id: str, name: str) -> Any:
    """The variable's value; AssertionError naming it when its status is Bad."""
    idx = await c.get_namespace_index(NAMESPACE)
    data = await c.get_node(ua.NodeId(f"{loop_id}.{name}", idx)).read_data_value(raise_on_bad_status=False)
    assert data.StatusCode.is_good(), f"{loop_id}.{name}: {data.StatusCode.name}"
    return data.Value.Value


async def until(predicate: Callable[[], Awaitable[Any]], timeout: float, what: str) -> Any:
    """Await ``predicate()`` every 50 ms until it is true (returned); AssertionError naming ``what`` after
    ``timeout`` wall seconds."""
    deadline = time.monotonic() + timeout
    while not (result := await predicate()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)
    return result


async def now(x: Any) -> Any:
    """``x`` as an awaitable (a plain condition for :func:`until`)."""
    return x


class Changes:
    """A subscription handler that keeps every data change (by the name given in ``names``) and every event."""

    def __init__(self) -> None:
        self.values: dict[str, list[Any]] = {}
        self.events: list[Any] = []
        self.names: dict[ua.NodeId, str] = {}

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.values.setdefault(self.names[node.nodeid], []).append(val)

    def event_notification(self, event: Any) -> None:
        self.events.append(event)
