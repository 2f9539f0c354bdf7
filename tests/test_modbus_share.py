"""Links that scale: one connection per Modbus device shared by its links, pipelined requests, the monitor's
one-request reading — against the real pymodbus server of the simulated PLCs (drivers.modbus_server) on localhost.

Each unit of a server is its own PLC with its own set point (10 × unit), so an answer taken for another request
shows as a wrong set point. Waits are on conditions with generous deadlines; nothing asserts a duration.
"""

from __future__ import annotations

import asyncio
import struct
from dataclasses import replace

import pytest

from autotuner.engine.plant.expression import parse_process
from drivers.link import LinkError, Mode, Sample
from drivers.modbus_link import ModbusLink
from drivers.modbus_map import DEFAULT_MAP, ModbusMap
from drivers.modbus_plant import serve_plant
from drivers.modbus_server import serve_units
from drivers.simplc import SimulatedPlc

from helpers import until

PLANT = "exp(-s)/(2*s+1)"
BOUND = 30.0  # no test may take longer than this, whatever happens


def arun(coro):
    """Run ``coro`` with an overall bound (a hang is a failure, not a stuck suite)."""
    async def bounded():
        return await asyncio.wait_for(coro, BOUND)
    return asyncio.run(bounded())


def plcs(n: int) -> dict[int, SimulatedPlc]:
    """Units 1..n, unit k at rest at PV = MV = SP = 10·k (the plant's gain is 1; nothing ticks them)."""
    return {unit: SimulatedPlc(parse_process(PLANT), pv0=10.0 * unit, mv0=10.0 * unit) for unit in range(1, n + 1)}


def links(port: int, units, **kw) -> list[ModbusLink]:
    return [ModbusLink.tcp("127.0.0.1", port, unit=u, **kw) for u in units]


async def close_all(*items) -> None:
    for item in items:
        await item.close()


# -- the server answers pipelined requests -----------------------------------------------------------------------

def _frame(tid: int, unit: int) -> bytes:
    pdu = struct.pack(">BHH", 3, DEFAULT_MAP["sp"].address, 2)  # read holding registers: sp (float32)
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def _answers(reader: asyncio.StreamReader, n: int) -> list[tuple[int, int, float]]:
    """``n`` answers to reads of sp: (transaction id, unit, sp)."""
    out = []
    for _ in range(n):
        tid, protocol, length, unit = struct.unpack(">HHHB", await reader.readexactly(7))
        pdu = await reader.readexactly(length - 1)
        assert protocol == 0 and pdu[:2] == b"\x03\x04", pdu
        out.append((tid, unit, struct.unpack(">f", pdu[2:6])[0]))
    return out


def test_the_server_answers_every_pipelined_request_with_its_own_transaction_id():
    # 60 requests to units 1..3 in one write (pymodbus 3.16.1's own handler answered the first only), then unit 2
    # hung: units 1 and 3 are answered past it, and unit 2's answers come when it is released — out of order.
    async def main():
        server = await serve_units(plcs(3))
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        try:
            sent = [(1000 + i, i % 3 + 1) for i in range(60)]
            writer.write(b"".join(_frame(tid, unit) for tid, unit in sent))
            got = await _answers(reader, 60)
            assert sorted(got) == [(tid, unit, 10.0 * unit) for tid, unit in sent]

            server.hang(True, unit=2)
            writer.write(b"".join(_frame(2000 + unit, unit) for unit in (1, 2, 3)))
            first = await _answers(reader, 2)
            assert sorted(first) == [(2001, 1, 10.0), (2003, 3, 30.0)]
            assert server.held == 1
            server.hang(False)
            assert await _answers(reader, 1) == [(2002, 2, 20.0)]
        finally:
            writer.close()
            await server.close()
    arun(main())


# -- one connection per device, reference counted -----------------------------------------------------------------

def test_links_to_one_device_share_one_connection_until_the_last_closes():
    async def main():
        units = plcs(3)
        server = await serve_units(units)
        a, b, c = links(server.port, (1, 2, 3), timeout=2.0)
        try:
            await a.open()
            await b.open()
            assert [await a.read_sample(), await b.read_sample()] == [
                Sample(10.0, 10.0, 10.0, Mode.AUTO, units[1].boot), Sample(20.0, 20.0, 20.0, Mode.AUTO, units[2].boot)]
            assert (server.accepted, server.connections) == (1, 1)
            assert a.health()["links"] == 2 and a.health()["connected"]
            await a.close()
            assert not a.health()["connected"] and b.health()["links"] == 1
            assert (await b.read_sample()).sp == 20.0  # b's share keeps the connection
            assert server.connections == 1
            await c.write_mv(31.0)  # a call without open() takes a share too
            assert server.plcs[3].hv == 31.0 and b.health()["links"] == 2 and server.accepted == 1
            await b.close()
            assert server.connections == 1
            await c.close()  # the last share: the connection closes
            await until(lambda: server.connections == 0, 5.0, "the connection closed by the last link")
            await a.open()  # a new share opens a new connection
            assert (await a.read_pv()) == 10.0 and server.accepted == 2
        finally:
            await close_all(a, b, c, server)
    arun(main())


def test_fifty_links_with_pipeline_16_keep_16_requests_outstanding_and_each_gets_its_own_units_answer():
    async def main():
        server = await serve_units(plcs(50))
        group = links(server.port, range(1, 51), timeout=10.0, pipeline=16)
        try:
            for link in group:
                await link.open()
            # Held by the server, the device keeps at most 16 requests outstanding; the other 34 wait their turn.
            server.hang(True)
            reads = [asyncio.create_task(link.read_sample()) for link in group]
            device = group[0]
            await until(lambda: server.held == 16 and device.health()["waiting"] == 34, 10.0, "16 held, 34 waiting")
            assert device.health()["outstanding"] == 16
            server.hang(False)
            samples = await asyncio.gather(*reads)
            assert [s.sp for s in samples] == [10.0 * unit for unit in range(1, 51)]
            # And flowing: 20 rounds of every link at once, each answer its own unit's.
            for _ in range(20):
                samples = await asyncio.gather(*(link.read_sample() for link in group))
                assert [(s.pv, s.sp) for s in samples] == [(10.0 * u, 10.0 * u) for u in range(1, 51)]
            assert (server.accepted, device.health()["links"]) == (1, 50)
            assert device.health()["late_answers"] == 0 and device.health()["dropped"] == 0
        finally:
            await close_all(*group, server)
    arun(main())


def test_pipeline_1_sends_one_request_at_a_time_and_the_smallest_pipeline_of_the_links_wins():
    async def main():
        server = await serve_units(plcs(3))
        many, one, other = (ModbusLink.tcp("127.0.0.1", server.port, unit=u, timeout=10.0, pipeline=p)
                            for u, p in ((1, 16), (2, 1), (3, 16)))
        try:
            await many.open()
            assert many.health()["pipeline"] == 16
            await one.open()
            await other.open()
            assert many.health()["pipeline"] == 1  # one link says the device takes one at a time: all get one
            server.hang(True)
            reads = [asyncio.create_task(link.read_pv()) for link in (many, one, other)]
            await until(lambda: server.held == 1 and many.health()["waiting"] == 2, 10.0, "1 held, 2 waiting")
            server.hang(False)
            assert await asyncio.gather(*reads) == [10.0, 20.0, 30.0]
            await one.close()
            assert many.health()["pipeline"] == 16
        finally:
            await close_all(many, one, other, server)
    arun(main())


# -- timeouts: a late answer is never taken for another request ---------------------------------------------------

def test_a_timed_out_request_does_not_corrupt_another_links_next_answer():
    # Pipeline 4: unit 1 hangs; its request times out while unit 2 keeps answering, so only that transaction is
    # dropped — no reconnection — and its late answer, when it comes, is discarded.
    async def main():
        server = await serve_units(plcs(2))
        stuck = ModbusLink.tcp("127.0.0.1", server.port, unit=1, timeout=0.5, retries=0, pipeline=4)
        fine = ModbusLink.tcp("127.0.0.1", server.port, unit=2, timeout=5.0, retries=0, pipeline=4)
        try:
            await stuck.open()
            await fine.open()
            server.hang(True, unit=1)
            waiting = asyncio.create_task(stuck.read_pv())
            seen = []
            while not waiting.done():
                seen.append(await fine.read_sample())
            with pytest.raises(LinkError, match=r"reading pv .*no answer within 0.5 s \(gave up after 1 attempt\)"):
                await waiting
            assert seen and all(s.sp == 20.0 for s in seen)
            server.hang(False)  # the held request is answered now: late
            await until(lambda: fine.health()["late_answers"] == 1, 5.0, "the late answer discarded")
            for _ in range(5):
                assert (await fine.read_sample()).sp == 20.0
                assert (await stuck.read_sample()).sp == 10.0
            assert server.accepted == 1 and fine.health()["dropped"] == 0
        finally:
            await close_all(stuck, fine, server)
    arun(main())


def test_a_device_silent_for_a_whole_timeout_is_reconnected_and_the_old_answer_never_read():
    # Pipeline 1: unit 1's request hangs and nothing else is answered meanwhile — the connection is taken for dead
    # and dropped; the other link's next request goes over a new connection and gets its own answer.
    async def main():
        server = await serve_units(plcs(2))
        stuck, fine = links(server.port, (1, 2), timeout=0.5, retries=0)
        try:
            await fine.open()
            assert (await fine.read_pv()) == 20.0
            server.hang(True, unit=1)
            with pytest.raises(LinkError, match=r"no answer within 0.5 s"):
                await stuck.read_pv()
            assert fine.health()["dropped"] == 1 and not fine.health()["connected"]
            assert (await fine.read_sample()).sp == 20.0
            assert server.accepted == 2
            server.hang(False)
            assert (await stuck.read_sample()).sp == 10.0
            assert (await fine.read_sample()).sp == 20.0
        finally:
            await close_all(stuck, fine, server)
    arun(main())


def test_a_request_waiting_for_its_turn_times_out_by_its_own_timeout_without_touching_the_one_outstanding():
    async def main():
        server = await serve_units(plcs(2))
        slow = ModbusLink.tcp("127.0.0.1", server.port, unit=1, timeout=10.0, retries=0)
        hurried = ModbusLink.tcp("127.0.0.1", server.port, unit=2, timeout=0.3, retries=0)
        try:
            server.hang(True, unit=1)
            outstanding = asyncio.create_task(slow.read_pv())
            await until(lambda: server.held == 1, 5.0, "the slow link's request held")
            with pytest.raises(LinkError, match=r"no answer within 0.3 s \(not sent: 1 requests waiting for their "
                                                r"answers, pipeline 1\) \(gave up after 1 attempt\)"):
                await hurried.read_pv()
            assert not outstanding.done() and slow.health()["dropped"] == 0
            server.hang(False)
            assert await outstanding == 10.0
            assert await hurried.read_pv() == 20.0 and server.accepted == 1
        finally:
            await close_all(slow, hurried, server)
    arun(main())


def test_a_call_cancelled_while_others_wait_leaves_them_their_answers():
    async def main():
        server = await serve_units(plcs(3))
        a, b, c = links(server.port, (1, 2, 3), timeout=10.0, pipeline=8)
        try:
            server.hang(True, unit=1)
            cancelled = asyncio.create_task(a.read_pv())
            await until(lambda: server.held == 1, 5.0, "a's request held")
            assert [await b.read_pv(), await c.read_pv()] == [20.0, 30.0]
            cancelled.cancel()
            with pytest.raises(asyncio.CancelledError):
                await cancelled
            server.hang(False)
            await until(lambda: b.health()["late_answers"] == 1, 5.0, "the cancelled request's answer discarded")
            assert [await a.read_pv(), await b.read_pv(), await c.read_pv()] == [10.0, 20.0, 30.0]
        finally:
            await close_all(a, b, c, server)
    arun(main())


class _Misbehaving:
    """A raw TCP "device": answers each request with ``answer(request frame)``."""

    def __init__(self, answer) -> None:
        self.answer = answer
        self.connections = 0

    async def start(self) -> int:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        return self.server.sockets[0].getsockname()[1]

    async def _serve(self, reader, writer) -> None:
        self.connections += 1
        try:
            while True:
                head = await reader.readexactly(7)
                body = await reader.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
                writer.write(self.answer(head + body))
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()

    async def close(self) -> None:
        self.server.close()


def _sp_answer(tid: int, unit: int, protocol: int = 0) -> bytes:
    pdu = b"\x03\x04" + struct.pack(">f", 77.0)
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


def test_answers_with_another_transaction_id_are_discarded_never_taken():
    async def main():
        device = _Misbehaving(lambda f: _sp_answer((struct.unpack(">H", f[:2])[0] + 1000) % 65536, f[6]))
        port = await device.start()
        link = ModbusLink.tcp("127.0.0.1", port, timeout=0.3, retries=1)
        try:
            with pytest.raises(LinkError, match=r"no answer within 0.3 s \(gave up after 2 attempts\)"):
                await link.read_state()
            assert link.health()["late_answers"] == 2 and link.health()["dropped"] == 0  # heard: not dead
        finally:
            await close_all(link, device)
    arun(main())


def test_a_frame_that_is_not_modbus_tcp_drops_the_connection():
    async def main():
        device = _Misbehaving(lambda f: _sp_answer(struct.unpack(">H", f[:2])[0], f[6], protocol=7))
        port = await device.start()
        link = ModbusLink.tcp("127.0.0.1", port, timeout=2.0, retries=1)
        try:
            with pytest.raises(LinkError, match=r"not Modbus TCP \(protocol id 7, length 7\) \(gave up after 2"):
                await link.read_pv()
            assert link.health()["dropped"] == 2 and device.connections == 2
        finally:
            await close_all(link, device)
    arun(main())


def test_a_device_restart_is_picked_up_by_every_link_sharing_it():
    async def main():
        units = plcs(2)
        server = await serve_units(units)
        port = server.port
        a, b = links(port, (1, 2), timeout=0.3, retries=1)
        try:
            await a.open()
            await b.open()
            assert [await a.read_pv(), await b.read_pv()] == [10.0, 20.0]
            await server.close()
            for link in (a, b):
                with pytest.raises(LinkError):
                    await link.read_pv()
            server = await serve_units(units, port=port)
            assert [await a.read_sample(), await b.read_sample()] == [
                Sample(10.0, 10.0, 10.0, Mode.AUTO, units[1].boot), Sample(20.0, 20.0, 20.0, Mode.AUTO, units[2].boot)]
            assert server.accepted == 1
        finally:
            await close_all(a, b, server)
    arun(main())


# -- RTU: one client per serial line -------------------------------------------------------------------------------

def test_rtu_links_to_units_of_one_line_share_its_client():
    # RTU framing over TCP (pyserial's socket:// URL): the serial path without hardware.
    async def main():
        server = await serve_units(plcs(2), rtu_framing=True)
        port = f"socket://127.0.0.1:{server.port}"
        a, b = (ModbusLink.rtu(port, 115200, unit=u, timeout=2.0) for u in (1, 2))
        other_speed = ModbusLink.rtu(port, 9600, unit=2, timeout=2.0)
        try:
            await a.open()
            await b.open()
            both = await asyncio.gather(*(link.read_sample() for _ in range(5) for link in (a, b)))
            assert [s.sp for s in both] == [10.0, 20.0] * 5
            await b.write_mv(33.0)
            assert server.plcs[2].hv == 33.0 and server.accepted == 1 and a.health()["links"] == 2
            with pytest.raises(LinkError, match=r"open at 115200 baud 8N1 by other loops; this link asks for 9600"):
                await other_speed.open()
        finally:
            await close_all(a, b, other_speed, server)
    arun(main())


# -- the monitor's reading -------------------------------------------------------------------------------------------

def test_read_sample_is_one_request_with_the_default_map_and_two_without_the_copies():
    # (a map without the copies, as a PLC's own map would be, without a boot token either)
    without = ModbusMap({n: r for n, r in DEFAULT_MAP.registers.items() if n not in ("sp_in", "mode_in", "boot")})

    async def main():
        units = plcs(1)
        units[1].mode = Mode.MAN
        units[1].hv = 12.5
        units[1].tick()
        server = await serve_units(units)
        plain, old = (ModbusLink.tcp("127.0.0.1", server.port, map=m, timeout=2.0) for m in (DEFAULT_MAP, without))
        try:
            expected = Sample(pv=pytest.approx(units[1].pv, rel=1e-6), mv=12.5, sp=10.0, mode=Mode.MAN,
                              boot=units[1].boot)
            assert await plain.read_sample() == expected and plain.requests == 1
            assert await old.read_sample() == replace(expected, boot=None) and old.requests == 2
            units[1].nan_pv = True
            with pytest.raises(LinkError, match=r"\bpv is not a number"):
                await plain.read_sample()
        finally:
            await close_all(plain, old, server)
    arun(main())


@pytest.mark.parametrize(("url", "needle"), [
    ("modbus://h/1?pipeline=0", "pipeline=0 is outside 1..128"),
    ("modbus://h/1?pipeline=129", "outside 1..128"),
    ("modbus://h/1?pipeline=many", "pipeline='many' is not valid"),
    ("modbus+rtu:///dev/ttyUSB0?pipeline=4", "pipeline is for Modbus TCP"),
])
def test_bad_pipeline_options_are_clear_value_errors(url, needle):
    with pytest.raises(ValueError, match="bad Modbus URL") as info:
        ModbusLink.from_url(url)
    assert needle in str(info.value)


def test_pipeline_option_parsed():
    assert ModbusLink.from_url("modbus://h:5020/3?pipeline=16").pipeline == 16
    assert ModbusLink.from_url("modbus://h:5020/3").pipeline == 1


def test_the_plant_gives_pipelined_urls_its_links_share_one_connection_per_server():
    async def main():
        async with await serve_plant(3, parse_process(PLANT), ts=0.1) as plant:
            assert plant.url(2) == f"modbus://127.0.0.1:{plant.port}/2"
            assert plant.url(2, 16) == f"modbus://127.0.0.1:{plant.port}/2?pipeline=16"
            group = [ModbusLink.from_url(plant.url(k, 16)) for k in (1, 2, 3)]
            try:
                samples = await asyncio.gather(*(link.read_sample() for link in group))
                assert samples == [Sample(pytest.approx(plc.pv, rel=1e-6), pytest.approx(plc.mv, rel=1e-6), plc.sp,
                                          plc.mode, plc.boot) for plc in plant.plcs]
                assert group[0].health()["pipeline"] == 16 and plant.servers[0].accepted == 1
            finally:
                await close_all(*group)
    arun(main())
