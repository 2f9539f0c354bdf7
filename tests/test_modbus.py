"""Modbus: register map coding, YAML maps, and the link against a real pymodbus server on localhost.

No mocks: every link test starts :func:`drivers.modbus_server.serve_modbus`
on an ephemeral localhost port and talks to it with the real pymodbus client.
Async tests run under ``asyncio.run`` with an overall bound, so a hang fails
the test instead of blocking the suite.
"""

from __future__ import annotations

import asyncio
import math
import struct
import time

import pytest
from pymodbus.client import AsyncModbusTcpClient

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from drivers.link import LinkError, LoopState, Mode, TuneFlags
from drivers.modbus_link import ModbusLink
from drivers.modbus_map import (
    DEFAULT_MAP,
    REQUIRED,
    SIGNALS,
    MapError,
    ModbusMap,
    Register,
    load_map,
    map_from_dict,
    ti_from_wire,
    ti_to_wire,
)
from drivers.modbus_server import serve_modbus
from drivers.simplc import SimulatedPlc

PLANT = "exp(-s)/(2*s+1)"
BOUND = 10.0  # no test may take longer than this, whatever happens


def arun(coro):
    """Run ``coro`` to completion with an overall bound (a hang is a failure, not a stuck suite)."""
    async def bounded():
        return await asyncio.wait_for(coro, BOUND)
    return asyncio.run(bounded())


def make_plc(**kw) -> SimulatedPlc:
    return SimulatedPlc(parse_process(PLANT), **kw)


# -- coding: every type, word and byte order, against struct ------------------------------

_FMT = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f", "float64": "d"}
_SAMPLES = {
    "int16": [-32768, -1234, 0, 1, 32767],
    "uint16": [0, 1, 4660, 65535],
    "int32": [-(2**31), -123456789, 0, 987654321, 2**31 - 1],
    "uint32": [0, 1, 0x12345678, 2**32 - 1],
    "float32": [0.0, 1.5, -2.75, 12345.5, 3.0e-5],
    "float64": [0.0, math.pi, -1.0e300, 123456.789012345],
}


def struct_words(value, type_: str, word_order: str, byte_order: str) -> list[int]:
    """The registers computed independently: pack big-endian, then reorder words / swap bytes."""
    data = struct.pack(">" + _FMT[type_], value)
    if byte_order == "little":
        data = b"".join(data[i + 1:i + 2] + data[i:i + 1] for i in range(0, len(data), 2))
    words = [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data), 2)]
    if word_order == "little":
        words.reverse()
    return words


@pytest.mark.parametrize("byte_order", ["big", "little"])
@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize("type_", list(_FMT))
def test_encode_decode_every_type_and_order(type_, word_order, byte_order):
    reg = Register("holding", 10, type_, word_order=word_order, byte_order=byte_order)
    for value in _SAMPLES[type_]:
        expected = struct_words(value, type_, word_order, byte_order)
        assert reg.encode(value) == expected, (type_, word_order, byte_order, value)
        back = reg.decode(expected)
        if type_ == "float32":
            assert back == struct.unpack(">f", struct.pack(">f", value))[0]
        else:
            assert back == value


def test_word_and_byte_order_names_the_usual_layouts():
    # 0x11223344 as ABCD, CDAB, BADC, DCBA.
    v = 0x11223344
    assert Register("input", 0, "uint32").encode(v) == [0x1122, 0x3344]
    assert Register("input", 0, "uint32", word_order="little").encode(v) == [0x3344, 0x1122]
    assert Register("input", 0, "uint32", byte_order="little").encode(v) == [0x2211, 0x4433]
    assert Register("input", 0, "uint32", word_order="little", byte_order="little").encode(v) == [0x4433, 0x2211]


def test_scaling_raw_to_engineering():
    reg = Register("holding", 0, "int16", scale=0.1, offset=-50.0)  # eng = raw/10 − 50
    words = reg.encode(12.3)
    assert words == struct_words(623, "int16", "big", "big")
    assert reg.decode(words) == pytest.approx(12.3)
    assert reg.decode(struct_words(-100, "int16", "big", "big")) == pytest.approx(-60.0)
    f = Register("input", 0, "float32", scale=2.0, offset=1.0)
    assert f.decode(struct_words(10.0, "float32", "big", "big")) == 21.0
    assert f.encode(21.0) == struct_words(10.0, "float32", "big", "big")


def test_encode_refuses_what_the_type_cannot_hold():
    with pytest.raises(ValueError, match="range"):
        Register("holding", 0, "int16").encode(40000)
    with pytest.raises(ValueError, match="range"):
        Register("holding", 0, "uint16").encode(-1)
    with pytest.raises(ValueError, match="range"):
        Register("holding", 0, "uint16", scale=0.01).encode(700.0)  # raw 70000
    with pytest.raises(ValueError):
        Register("holding", 0, "float32").encode(math.nan)
    with pytest.raises(ValueError):
        Register("holding", 0, "float32").encode(1e39)
    # NaN decodes as NaN: the link, not the map, refuses it as data.
    assert math.isnan(Register("input", 0, "float32").decode(struct_words(math.nan, "float32", "big", "big")))


def test_bits_and_map_level_calls():
    assert DEFAULT_MAP.encode("tbsy", True) == [1]
    assert DEFAULT_MAP.encode("te", False) == [0]
    assert DEFAULT_MAP.decode("tune", [True]) == 1.0
    assert DEFAULT_MAP.encode("mode", 1) == [1]
    assert DEFAULT_MAP.decode("pv", struct_words(42.5, "float32", "big", "big")) == 42.5


def test_ti_wire_convention():
    assert ti_to_wire(math.inf) == 0.0
    assert ti_from_wire(0.0) == math.inf
    assert ti_from_wire(ti_to_wire(3.5)) == 3.5


def test_default_map_layout():
    m = DEFAULT_MAP
    assert set(m.registers) == set(SIGNALS)
    assert (m["pv"].table, m["pv"].address, m["pv"].type) == ("input", 0, "float32")
    assert (m["mv"].table, m["mv"].address) == ("input", 2)
    assert (m["sp"].table, m["sp"].address) == ("holding", 0)
    assert (m["hv"].table, m["hv"].address) == ("holding", 2)
    assert [m[s].address for s in ("k", "ti", "td", "nd", "b", "c", "ite")] == [4, 6, 8, 10, 12, 14, 16]
    assert (m["mode"].table, m["mode"].address, m["mode"].type) == ("holding", 18, "uint16")
    assert [(m[s].table, m[s].address) for s in ("tune", "tbrk", "tbsy", "te")] == [
        ("coil", 0), ("coil", 1), ("coil", 2), ("coil", 3)]
    # Its dict form is a valid map again.
    assert map_from_dict(DEFAULT_MAP.as_dict()).registers == DEFAULT_MAP.registers


# -- YAML maps ---------------------------------------------------------------------------

GOOD_YAML = """\
word_order: little
signals:
  pv:   {table: input, address: 100, type: int16, scale: 0.1}
  mv:   {table: input, address: 101, type: int16, scale: 0.1}
  sp:   {table: holding, address: 200, type: int16, scale: 0.1}
  hv:   {table: holding, address: 201, type: int16, scale: 0.1}
  mode: {table: holding, address: 202, type: uint16}
  k:    {table: holding, address: 204, type: float32}
  ti:   {table: holding, address: 206, type: float32, word_order: big}
  tune: {table: discrete_input, address: 7}
  tbsy: {table: coil, address: 8}
"""


def write(tmp_path, text, name="map.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_yaml_map_loads_with_defaults(tmp_path):
    m = load_map(write(tmp_path, GOOD_YAML))
    assert m["pv"] == Register("input", 100, "int16", word_order="little", scale=0.1)
    assert m["ti"].word_order == "big" and m["k"].word_order == "little"
    assert m["tune"].type == "bool" and m["tbsy"].table == "coil"
    assert "td" not in m and "ite" not in m
    assert m.decode("pv", [523]) == pytest.approx(52.3)


@pytest.mark.parametrize(
    ("change", "needles"),
    [
        (("  pv:   {table: input, address: 100, type: int16, scale: 0.1}",
          "  pv:   {table: inputs, address: 100}"), ["'pv'", "unknown table 'inputs'"]),
        (("  k:    {table: holding, address: 204, type: float32}",
          "  k:    {table: holding, address: 204, type: float16}"), ["'k'", "unknown type 'float16'"]),
        (("  ti:   {table: holding, address: 206, type: float32, word_order: big}",
          "  ti:   {table: holding, address: 205, type: float32}"), ["'ti'", "overlaps", "'k'"]),
        (("  mode: {table: holding, address: 202, type: uint16}\n", ""), ["missing required", "mode"]),
        (("  hv:   {table: holding, address: 201, type: int16, scale: 0.1}",
          "  hv:   {table: input, address: 201, type: int16}"), ["'hv'", "holding register or a coil"]),
        (("  tbsy: {table: coil, address: 8}", "  tbsy: {table: holding, address: 9, type: uint16}"),
         ["'tbsy'", "coil or discrete_input"]),
        (("  tune: {table: discrete_input, address: 7}", "  tune: {table: discrete_input, address: 7, type: int16}"),
         ["'tune'", "type must be bool"]),
        (("  tbsy: {table: coil, address: 8}", "  tbsy: {table: coil, address: 8}\n  foo: {table: coil, address: 9}"),
         ["unknown signal 'foo'"]),
        (("  sp:   {table: holding, address: 200, type: int16, scale: 0.1}",
          "  sp:   {table: holding, address: 200, type: int16, scale: 0}"), ["'sp'", "scale must be non-zero"]),
        (("  sp:   {table: holding, address: 200, type: int16, scale: 0.1}",
          "  sp:   {table: holding, type: int16}"), ["'sp'", "missing 'address'"]),
        (("  sp:   {table: holding, address: 200, type: int16, scale: 0.1}",
          "  sp:   {table: holding, address: 65535, type: float32}"), ["'sp'", "outside"]),
        (("  sp:   {table: holding, address: 200, type: int16, scale: 0.1}",
          "  sp:   {table: holding, address: 200, typo: int16}"), ["'sp'", "unknown key", "typo"]),
        (("word_order: little", "word_order: middle"), ["word_order"]),
    ],
)
def test_yaml_map_errors_name_file_signal_and_problem(tmp_path, change, needles):
    old, new = change
    assert old in GOOD_YAML
    path = write(tmp_path, GOOD_YAML.replace(old, new), "plant-map.yaml")
    with pytest.raises(MapError) as info:
        load_map(path)
    msg = str(info.value)
    assert str(path) in msg
    for needle in needles:
        assert needle in msg, msg


def test_yaml_file_problems(tmp_path):
    with pytest.raises(MapError, match="cannot read"):
        load_map(tmp_path / "nope.yaml")
    with pytest.raises(MapError, match="not valid YAML"):
        load_map(write(tmp_path, "signals: [unclosed"))
    with pytest.raises(MapError, match="signals"):
        load_map(write(tmp_path, "- just a list"))


def test_overlap_across_tables_is_fine_but_not_within_one():
    regs = dict(DEFAULT_MAP.registers)
    regs["pv"] = Register("input", 0)  # input 0 while sp is holding 0: different tables
    ModbusMap(regs)
    regs["mv"] = Register("input", 1)
    with pytest.raises(MapError, match="'mv'.*overlaps signal 'pv'"):
        ModbusMap(regs)


# -- the link against a real server ----------------------------------------------------------

async def started(plc=None, **server_kw):
    plc = plc or make_plc()
    server = await serve_modbus(plc, **server_kw)
    return plc, server


def test_server_gets_an_ephemeral_port_and_link_reads_pv():
    async def main():
        plc, server = await started()
        assert server.port > 0
        # Move the plant off its steady state so PV is not a round number.
        plc.mode = Mode.MAN
        plc.hv = 80.0
        while plc.t < 2.0:  # past the dead time
            plc.tick()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.5)
        try:
            await link.open()
            n = link.requests
            pv = await link.read_pv()
            assert link.requests - n == 1  # pv alone: one request
            assert pv == pytest.approx(plc.pv, rel=1e-6)  # float32 on the wire
            assert pv != 50.0
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_writes_reach_the_plc_and_state_reads_back():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.5)
        try:
            await link.open()
            state = await link.read_state()
            assert isinstance(state, LoopState)
            assert state.mode is Mode.AUTO
            assert state.mv == pytest.approx(plc.mv, rel=1e-6)
            assert state.sp == pytest.approx(plc.sp, rel=1e-6)
            assert state.gains.k == pytest.approx(plc.gains.k, rel=1e-6)
            assert state.gains.ti == pytest.approx(plc.gains.ti, rel=1e-6)

            await link.write_mode(Mode.MAN)
            assert plc.mode is Mode.MAN
            await link.write_mv(37.25)
            assert plc.hv == 37.25
            plc.tick()  # in MAN the PLC applies the manual MV
            state = await link.read_state()
            assert state.mode is Mode.MAN and state.mv == 37.25

            # Gains exactly representable in float32; ti = inf travels as 0.
            g = Gains(k=2.5, ti=math.inf, td=0.5, nd=8.0, b=0.75, c=0.25)
            n = link.requests
            await link.write_gains(g)
            assert link.requests - n == 1  # k..c adjacent: one write
            assert plc.gains == g
            assert (await link.read_state()).gains == g
            g2 = Gains(k=-1.5, ti=12.0)
            await link.write_gains(g2)
            assert plc.gains == g2 and (await link.read_state()).gains == g2

            await link.write_mode(Mode.AUTO)
            assert plc.mode is Mode.AUTO
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_handshake_flags_both_ways():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.5)
        try:
            await link.write_flags(TuneFlags(tbsy=True, te=False, ite=12.5))
            assert (plc.flags.tbsy, plc.flags.te, plc.flags.ite) == (True, False, 12.5)
            assert not plc.flags.tune and not plc.flags.tbrk  # the device's inputs are not touched
            plc.flags = TuneFlags(tune=True, tbrk=True, tbsy=False, te=True, ite=3.0)
            assert await link.read_flags() == TuneFlags(tune=True, tbrk=True, tbsy=False, te=True, ite=3.0)
            await link.write_flags(TuneFlags(tbsy=False, te=True, ite=7.0))
            assert plc.flags == TuneFlags(tune=True, tbrk=True, tbsy=False, te=True, ite=7.0)
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_nan_pv_is_a_link_error_naming_pv():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.5)
        try:
            plc.nan_pv = True
            with pytest.raises(LinkError, match=r"\bpv is not a number"):
                await link.read_pv()
            plc.nan_pv = False
            assert await link.read_pv() == pytest.approx(plc.pv, rel=1e-6)
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_exception_response_is_a_link_error():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.5)
        try:
            server.fail_with_exception(True)
            t0 = time.monotonic()
            with pytest.raises(LinkError, match=r"reading pv .*exception 4 \(device failure\)"):
                await link.read_pv()
            assert time.monotonic() - t0 < 0.5  # an answer, not retried
            with pytest.raises(LinkError, match="exception"):
                await link.read_state()
            await link.write_mv(10.0)  # writes still accepted by default (the loop can be restored)
            assert plc.hv == 10.0
            server.fail_with_exception(True, writes=True)
            with pytest.raises(LinkError, match=r"writing hv .*exception"):
                await link.write_mv(11.0)
            server.fail_with_exception(False)
            assert await link.read_pv() == pytest.approx(plc.pv, rel=1e-6)
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_device_refuses_bad_values_and_unknown_addresses():
    async def main():
        plc, server = await started()
        client = AsyncModbusTcpClient("127.0.0.1", port=server.port, timeout=0.5, retries=0, reconnect_delay=0)
        try:
            await client.connect()
            rr = await client.write_register(DEFAULT_MAP["mode"].address, 7, device_id=1)
            assert rr.isError() and rr.exception_code == 3
            assert plc.mode is Mode.AUTO
            rr = await client.read_holding_registers(500, count=2, device_id=1)
            assert rr.isError() and rr.exception_code == 2
            # k = 0 is not a controller: refused, gains unchanged.
            before = plc.gains
            rr = await client.write_registers(DEFAULT_MAP["k"].address, DEFAULT_MAP.encode("k", 0.0), device_id=1)
            assert rr.isError() and rr.exception_code == 3 and plc.gains == before
        finally:
            client.close()
            await server.close()
        # The link names the signal when the device says the address does not exist.
        regs = dict(DEFAULT_MAP.registers)
        regs["pv"] = Register("input", 40)
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, map=ModbusMap(regs), timeout=0.5)
        try:
            with pytest.raises(LinkError, match=r"reading pv \(input register 40 .*exception 2"):
                await link.read_pv()
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_server_stopped_is_a_link_error_within_the_timeout():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.2, retries=1)
        try:
            await link.open()
            await link.read_pv()
            await server.close()
            t0 = time.monotonic()
            with pytest.raises(LinkError, match="reading pv"):
                await link.read_pv()
            assert time.monotonic() - t0 < (1 + link.retries) * 2 * link.timeout + 0.3
            with pytest.raises(LinkError, match="writing hv"):
                await link.write_mv(1.0)
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_no_answer_is_a_link_error_not_a_hang():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.2, retries=1)
        try:
            await link.read_pv()
            server.hang(True)
            t0 = time.monotonic()
            with pytest.raises(LinkError, match=r"no answer within 0.2 s \(gave up after 2 attempts\)"):
                await link.read_pv()
            assert time.monotonic() - t0 < (1 + link.retries) * 2 * link.timeout + 0.3
            server.hang(False)
            assert await link.read_pv() == pytest.approx(plc.pv, rel=1e-6)
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_a_cancelled_call_leaves_the_link_usable():
    async def main():
        plc, server = await started()
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=1.0, retries=0)
        try:
            server.hang(True)
            task = asyncio.create_task(link.read_pv())
            await asyncio.sleep(0.1)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            server.hang(False)
            assert await link.read_pv() == pytest.approx(plc.pv, rel=1e-6)
            await link.write_mv(5.0)
            assert plc.hv == 5.0
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_reconnects_when_the_server_comes_back_on_the_same_port():
    async def main():
        plc, server = await started()
        port = server.port
        link = ModbusLink.tcp("127.0.0.1", port, timeout=0.2, retries=1)
        try:
            await link.read_pv()
            await server.close()
            with pytest.raises(LinkError):
                await link.read_pv()
            server = await serve_modbus(plc, port=port)
            await link.write_mv(21.0)  # no explicit open(): the next call reconnects
            assert plc.hv == 21.0
            assert await link.read_pv() == pytest.approx(plc.pv, rel=1e-6)
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_open_fails_cleanly_when_nothing_listens():
    async def main():
        plc, server = await started()
        port = server.port
        await server.close()
        link = ModbusLink.tcp("127.0.0.1", port, timeout=0.2)
        with pytest.raises(LinkError, match=f"127.0.0.1:{port}.*cannot connect"):
            await link.open()
        await link.close()
        await link.close()  # never raises
    arun(main())


def test_reads_follow_the_running_plant():
    async def main():
        from drivers.simplc import run
        plc, server = await started()
        plc.mode = Mode.MAN
        plc.hv = 90.0
        stop = asyncio.Event()
        plant = asyncio.create_task(run(plc, speed=20.0, stop=stop))
        link = ModbusLink.tcp("127.0.0.1", server.port, timeout=0.5)
        try:
            seen = []
            for _ in range(20):
                before = plc.pv
                pv = await link.read_pv()
                # The plant may tick while the answer travels; the PV rises monotonically.
                assert before * (1 - 1e-6) <= pv <= plc.pv * (1 + 1e-6)
                seen.append(pv)
                await asyncio.sleep(0.01)
            assert seen[-1] > seen[0]
        finally:
            stop.set()
            await plant
            await link.close()
            await server.close()
    arun(main())


def test_custom_map_served_and_read(tmp_path):
    m = load_map(write(tmp_path, GOOD_YAML))

    async def main():
        plc, server = await started(map=m)
        link = ModbusLink.tcp("127.0.0.1", server.port, map=m, timeout=0.5)
        try:
            assert await link.read_pv() == pytest.approx(plc.pv, abs=0.05)  # int16 in tenths
            await link.write_mv(12.34)
            assert plc.hv == pytest.approx(12.3)
            state = await link.read_state()
            assert state.gains.td == 0.0 and state.gains.nd == 10.0  # absent: defaults
            await link.write_gains(Gains(k=2.0, ti=4.0))
            assert plc.gains.k == 2.0 and plc.gains.ti == 4.0
            with pytest.raises(LinkError, match="no td"):
                await link.write_gains(Gains(k=2.0, ti=4.0, td=1.0))
            await link.write_flags(TuneFlags(tbsy=True, te=True, ite=5.0))  # te, ite absent: skipped
            assert plc.flags.tbsy and not plc.flags.te
            plc.flags = TuneFlags(tune=True)
            assert (await link.read_flags()).tune
        finally:
            await link.close()
            await server.close()
    arun(main())


def test_unit_id_is_used():
    async def main():
        plc, server = await started(unit=3)
        good = ModbusLink.tcp("127.0.0.1", server.port, unit=3, timeout=0.3, retries=0)
        bad = ModbusLink.tcp("127.0.0.1", server.port, unit=4, timeout=0.3, retries=0)
        try:
            assert await good.read_pv() == pytest.approx(plc.pv, rel=1e-6)
            with pytest.raises(LinkError, match=r"unit 4 answered Modbus exception 11 \(gateway no response\)"):
                await bad.read_pv()
        finally:
            await good.close()
            await bad.close()
            await server.close()
    arun(main())


def test_rtu_link_over_a_socket_port():
    # RTU framing over TCP, reached through pyserial's socket:// URL: the RTU client code path without hardware.
    async def main():
        plc, server = await started(rtu_framing=True)
        link = ModbusLink.rtu(f"socket://127.0.0.1:{server.port}", 115200, unit=1, timeout=0.5)
        try:
            await link.open()
            assert await link.read_pv() == pytest.approx(plc.pv, rel=1e-6)
            await link.write_mode(Mode.MAN)
            await link.write_mv(44.0)
            assert plc.mode is Mode.MAN and plc.hv == 44.0
        finally:
            await link.close()
            await server.close()
    arun(main())


# -- URLs ------------------------------------------------------------------------------------

def test_url_parsing(tmp_path):
    link = ModbusLink.from_url("modbus://10.0.0.5:5020/7")
    assert (link.name, link.unit, link.map) == ("modbus tcp 10.0.0.5:5020", 7, DEFAULT_MAP)
    link = ModbusLink.from_url("modbus://plc.local")
    assert (link.name, link.unit) == ("modbus tcp plc.local:502", 1)
    link = ModbusLink.from_url("modbus://[::1]:1502/2?timeout=0.25&retries=0")
    assert (link.name, link.unit, link.timeout, link.retries) == ("modbus tcp [::1]:1502", 2, 0.25, 0)
    link = ModbusLink.from_url("modbus+rtu:///dev/ttyUSB0?baudrate=9600&unit=3&parity=E")
    assert (link.name, link.unit) == ("modbus rtu /dev/ttyUSB0@9600", 3)
    path = write(tmp_path, GOOD_YAML)
    assert ModbusLink.from_url("modbus://h:1/1", map_path=str(path)).map["pv"].type == "int16"


@pytest.mark.parametrize(
    ("url", "needle"),
    [
        ("http://host:502/1", "scheme"),
        ("modbus://", "no host"),
        ("modbus://host:port/1", "port"),
        ("modbus://host:99999/1", "port"),
        ("modbus://host:502/abc", "unit id 'abc'"),
        ("modbus://host:502/300", "outside 0..255"),
        ("modbus://host/1?timeout=fast", "timeout"),
        ("modbus://host/1?speed=2", "unknown option"),
        ("modbus+rtu://", "no serial device"),
    ],
)
def test_bad_urls_are_clear_value_errors(url, needle):
    with pytest.raises(ValueError, match="bad Modbus URL") as info:
        ModbusLink.from_url(url)
    assert needle in str(info.value)


def test_required_signals_are_documented_subset():
    assert REQUIRED <= set(SIGNALS)


# -- the documentation matches the code ---------------------------------------------------------

def _docs() -> str:
    from pathlib import Path
    return (Path(__file__).resolve().parents[1] / "docs" / "modbus.md").read_text(encoding="utf-8")


def test_documented_default_map_is_the_default_map():
    import re
    tables = {"input register": "input", "holding register": "holding", "coil": "coil",
              "discrete input": "discrete_input"}
    rows = re.findall(r"^\| `(\w+)` \| ([a-z ]+) \| (\d+)(?:–\d+)? \| (\w+) \|", _docs(), re.M)
    documented = {name: (tables[table], int(addr), type_) for name, table, addr, type_ in rows}
    actual = {n: (r.table, r.address, r.type) for n, r in DEFAULT_MAP.registers.items()}
    assert documented == actual


def test_documented_yaml_example_loads():
    import re
    import yaml
    block = re.findall(r"```yaml\n(.*?)```", _docs(), re.S)[0]
    m = map_from_dict(yaml.safe_load(block), "docs/modbus.md")
    assert m["pv"].scale == 0.1 and m["k"].word_order == "little"
