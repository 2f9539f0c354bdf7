"""CAN link and simulated CAN node over python-can's virtual bus (no mocks), and the default DBC."""

from __future__ import annotations

import asyncio
import cmath
import contextlib
import itertools
import math
import struct
import time

import can
import cantools
import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.engine.outcome import Code
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.service.remote_tuning import field_config
from autotuner.service.link_session import HandBack, SessionPlan, tune_link
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.can_link import (CMD_SP, EPOCH_FRAMES, FENCE, FENCE_SIGNALS, REQUIRED, WATCHDOG_SIGNALS, CanLink,
                              default_dbc, epoch_from_wire, epoch_to_wire, gains_from_wire, gains_to_wire, load_dbc,
                              ti_from_wire, ti_to_wire)
from drivers.can_node import serve_can
from drivers.link import Fenced, LinkError, Mode, TuneFlags, Watchdog
from drivers.simplc import SimulatedPlc, run

PLANT = "exp(-s)/(2*s+1)"
PERIOD = 0.01  # wall seconds between the node's cyclic frames
_channels = itertools.count()


def f32(x: float) -> float:
    """``x`` as it comes back from an IEEE float32 signal."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def arun(coro, limit: float = 60.0):
    """Run ``coro`` with a hard bound, so a hang fails the test instead of stalling the suite."""
    return asyncio.run(asyncio.wait_for(coro, limit))


@contextlib.asynccontextmanager
async def rig(dbc=None, period=PERIOD, timeout=0.3, stale_after=None):
    """A simulated PLC served by a CAN node and a CanLink to it, on a fresh virtual channel.

    The link is opened first, so it receives every frame the node sends (what :func:`new_frames` counts on).
    """
    channel = f"test-can-{next(_channels)}"
    plc = SimulatedPlc(parse_process(PLANT))
    link = CanLink("virtual", channel, dbc=dbc, timeout=timeout, stale_after=stale_after)
    await link.open()
    node = await serve_can(plc, "virtual", channel, dbc=dbc, period=period)
    try:
        yield plc, node, link
    finally:
        await link.close()
        await node.close()


async def until(pred, limit: float = 30.0) -> bool:
    """Poll ``pred`` until it holds or ``limit`` seconds pass (generous: a loaded machine may be slow)."""
    deadline = time.monotonic() + limit
    while not pred() and time.monotonic() < deadline:
        await asyncio.sleep(0.002)
    return pred()


async def new_frames(link: CanLink, node) -> None:
    """Wait until the link has received a whole cycle of frames the node encoded after now.

    Frames received after now are not enough: under load a backlog of frames encoded from the PLC's earlier state
    is still on its way (the race that failed these tests 2 runs in 5 with two CPU burners). The node sends its
    cycle (AT_Process, AT_Status, AT_Setpoint, then maybe the gains) within one call on this event loop, so the
    three frames after the ones sent so far are a cycle encoded now; the link, opened before the node, receives
    every frame the node sends, in order.
    """
    target = node.stats["sent"] + 3
    assert await until(lambda: link.stats["frames"] + link.stats["bad_frames"] >= target)


# ------------------------------------------------------------------------- DBC

DB = cantools.database.load_file(str(default_dbc()))

IDS = {
    "AT_Process": 0x100, "AT_Status": 0x101, "AT_Setpoint": 0x102, "AT_Fence": 0x103,
    "AT_Gains1": 0x110, "AT_Gains2": 0x111, "AT_Gains3": 0x112,
    "AT_CmdMV": 0x200, "AT_CmdMode": 0x201, "AT_CmdSP": 0x202, "AT_CmdFlags": 0x203,
    "AT_CmdWatchdog": 0x204, "AT_Heartbeat": 0x205,
    "AT_CmdGains1": 0x210, "AT_CmdGains2": 0x211, "AT_CmdGains3": 0x212, "AT_CmdGainsApply": 0x213,
    "AT_Request": 0x220,
}


def test_default_dbc_ships_with_the_package_and_has_the_documented_ids():
    assert default_dbc().is_file()
    assert default_dbc().parent.name == "data" and default_dbc().parent.parent.name == "drivers"
    assert {m.name: m.frame_id for m in DB.messages} == IDS
    for m in DB.messages:
        assert not m.is_extended_frame and m.frame_id <= 0x7FF
        epoch = {"Epoch"} if m.name in (*EPOCH_FRAMES, *WATCHDOG_SIGNALS) else set()
        signals = {**REQUIRED, **WATCHDOG_SIGNALS, FENCE: FENCE_SIGNALS}[m.name]
        assert {s.name for s in m.signals} == set(signals) | epoch
    load_dbc()  # passes its own check


# Messages whose signals are two little-endian IEEE float32s, bytes 0-3 and 4-7.
FLOAT_PAIRS = {
    "AT_Process": ("PV", "MV"), "AT_Setpoint": ("SP", "HV"),
    "AT_Gains1": ("K", "Ti"), "AT_Gains2": ("Td", "N"), "AT_Gains3": ("B", "C"),
    "AT_CmdGains1": ("K", "Ti"), "AT_CmdGains2": ("Td", "N"), "AT_CmdGains3": ("B", "C"),
}


@pytest.mark.parametrize("name", sorted(FLOAT_PAIRS))
def test_float_pair_frames_are_two_little_endian_float32(name):
    a, b = FLOAT_PAIRS[name]
    raw = struct.pack("<ff", 12.375, -0.1)
    assert DB.encode_message(name, {a: 12.375, b: -0.1}) == raw
    out = DB.decode_message(IDS[name], raw)
    assert out == {a: 12.375, b: f32(-0.1)}
    nan = DB.decode_message(IDS[name], struct.pack("<ff", math.nan, math.inf))
    assert math.isnan(nan[a]) and nan[b] == math.inf


def test_single_float_command_frames():
    raw = struct.pack("<f", 42.5)
    assert DB.encode_message("AT_CmdSP", {"SP": 42.5}) == raw
    assert DB.decode_message(IDS["AT_CmdSP"], raw) == {"SP": 42.5}
    # The manual MV carries the sender's lease epoch, uint32 little-endian in bytes 4-7 (docs/can.md).
    raw = struct.pack("<fI", 42.5, 70000)
    assert DB.encode_message("AT_CmdMV", {"HV": 42.5, "Epoch": 70000}) == raw
    assert DB.decode_message(IDS["AT_CmdMV"], raw) == {"HV": 42.5, "Epoch": 70000}


def test_status_frame_layout():
    # byte 0: Mode, TUNE, TBRK, TBSY, TE in bits 0..4; byte 1: counter (low nibble); bytes 4-7: ite float32
    raw = bytes([0b1_0101, 0x0B, 0, 0]) + struct.pack("<f", 7.5)
    values = {"Mode": 1, "TUNE": 0, "TBRK": 1, "TBSY": 0, "TE": 1, "Counter": 11, "ITE": 7.5}
    assert DB.encode_message("AT_Status", values) == raw
    assert DB.decode_message(IDS["AT_Status"], raw, decode_choices=False) == values
    assert DB.decode_message(IDS["AT_Status"], raw)["Mode"] == "AUTO"


def test_command_bit_frames_layout():
    assert DB.encode_message("AT_CmdMode", {"Mode": 1, "Epoch": 3}) == b"\x01\0\0\0" + struct.pack("<I", 3)
    assert DB.decode_message(IDS["AT_CmdMode"], bytes(8), decode_choices=False) == {"Mode": 0, "Epoch": 0}
    # The flags carry a short epoch in bytes 1-3 (24 bits), the watchdog in bits 49-63 (15 bits): docs/can.md.
    raw = bytes([0b10, 0x56, 0x34, 0x12]) + struct.pack("<f", 3.0)
    assert DB.encode_message("AT_CmdFlags", {"TBSY": 0, "TE": 1, "Epoch": 0x123456, "ITE": 3.0}) == raw
    assert DB.decode_message(IDS["AT_CmdFlags"], raw) == {"TBSY": 0, "TE": 1, "Epoch": 0x123456, "ITE": 3.0}
    raw = struct.pack("<fHH", 50.0, 200, 1 | 0x7ABC << 1)
    values = {"WdMV": 50.0, "WdTime": 20.0, "WdMode": 1, "Epoch": 0x7ABC}
    assert DB.encode_message("AT_CmdWatchdog", values) == raw
    assert DB.decode_message(IDS["AT_CmdWatchdog"], raw, decode_choices=False) == values
    assert DB.encode_message("AT_Fence", {"Epoch": 6, "Fenced": 70000}) == struct.pack("<II", 6, 70000)
    assert DB.encode_message("AT_CmdGainsApply", {"Apply": 1, "Epoch": 2**32 - 1}) == b"\x01\0\0\0\xff\xff\xff\xff"
    assert DB.encode_message("AT_Heartbeat", {"Counter": 0x1234, "Epoch": 5}) == b"\x34\x12\0\0\x05\0\0\0"
    assert DB.encode_message("AT_Request", {"All": 1}) == b"\x01"


def test_no_integral_action_is_ti_zero_on_the_wire():
    assert ti_to_wire(math.inf) == 0.0 and ti_to_wire(2.5) == 2.5
    assert ti_from_wire(0.0) == math.inf and ti_from_wire(math.inf) == math.inf and ti_from_wire(2.5) == 2.5
    for bad in (math.nan, -1.0):
        with pytest.raises(ValueError):
            ti_from_wire(bad)
    g = Gains(k=-1.5, ti=math.inf, td=0.25, nd=8.0, b=0.5, c=0.0)
    wire = gains_to_wire(g)
    assert wire[0] == {"K": -1.5, "Ti": 0.0}
    assert gains_from_wire({**wire[0], **wire[1], **wire[2]}) == g


def test_load_dbc_errors(tmp_path):
    broken = tmp_path / "broken.dbc"
    broken.write_text(default_dbc().read_text().replace("AT_Request", "AT_Ask").replace(" Apply ", " Go "))
    with pytest.raises(ValueError, match="AT_Request.*|.*AT_CmdGainsApply.Apply"):
        load_dbc(broken)
    with pytest.raises(ValueError, match="cannot load DBC"):
        load_dbc(tmp_path / "missing.dbc")


# ------------------------------------------------------------------------- URL

def test_from_url():
    link = CanLink.from_url("can://virtual/autotuner")
    assert (link.interface, link.channel, link.timeout, link.stale_after) == ("virtual", "autotuner", 1.0, None)
    link = CanLink.from_url("can://slcan//dev/ttyACM0?bitrate=500000&timeout=0.2&stale_after=0.05")
    assert (link.interface, link.channel) == ("slcan", "/dev/ttyACM0")
    assert link.bus_kwargs == {"bitrate": 500000} and link.timeout == 0.2 and link.stale_after == 0.05


@pytest.mark.parametrize("url", [
    "modbus://localhost:502", "can://virtual", "can://virtual/", "can:///can0", "can:virtual/can0",
    "virtual/can0", "can://socketcan/can0?bitrate=fast", "can://socketcan/can0?speed=1",
    "can://socketcan/can0#x",
])
def test_bad_urls(url):
    with pytest.raises(ValueError, match="CAN link URL"):
        CanLink.from_url(url)


def test_unknown_interface_is_a_link_error():
    async def main():
        link = CanLink("no-such-interface", "x")
        with pytest.raises(LinkError, match="cannot open CAN interface"):
            await link.open()
        await link.close()
    arun(main())


def test_calls_on_a_closed_link_are_link_errors():
    async def main():
        link = CanLink("virtual", f"test-can-{next(_channels)}", timeout=0.1)
        with pytest.raises(LinkError, match="not open"):
            await link.read_pv()
        with pytest.raises(LinkError, match="not open"):
            await link.write_mv(1.0)
    arun(main())


# ----------------------------------------------------------------- link ↔ node

def test_read_pv_is_the_plc_pv_after_a_tick():
    async def main():
        async with rig() as (plc, node, link):
            assert await link.read_pv() == f32(plc.pv)
            plc.mode = Mode.MAN
            plc.hv = 80.0
            for _ in range(30):
                plc.tick()
            assert plc.pv != 50.0
            await new_frames(link, node)
            assert await link.read_pv() == f32(plc.pv)
            assert link.pv_age < 0.5
    arun(main())


def test_read_sample_is_pv_mv_sp_and_mode_from_the_cyclic_frames_and_stale_when_the_node_is_silent():
    async def main():
        async with rig(timeout=0.3) as (plc, node, link):
            plc.mode = Mode.MAN
            plc.hv = 80.0
            plc.sp = 61.5
            for _ in range(30):
                plc.tick()
            await new_frames(link, node)
            sample = await link.read_sample()
            assert (sample.pv, sample.mv, sample.sp, sample.mode) == (f32(plc.pv), f32(plc.mv), 61.5, Mode.MAN)
            assert sample.pv != 50.0 and sample.mv == 80.0
            node.silent = True
            deadline = time.monotonic() + HANG
            with pytest.raises(LinkError, match=r"stale PV: no fresh .*within 0.3 s"):
                while time.monotonic() < deadline:  # reads succeed only while the last frames are fresh
                    await link.read_sample()
                    await asyncio.sleep(PERIOD)
            node.silent = False
            await new_frames(link, node)
            assert (await link.read_sample()).sp == 61.5
    arun(main())


def test_links_on_one_channel_share_its_bus_until_the_last_closes():
    # The watch's link and the session's of one loop, and a third asking another bit rate.
    async def main():
        async with rig() as (plc, node, link):
            other = CanLink("virtual", link.channel, timeout=0.3)
            faster = CanLink("virtual", link.channel, timeout=0.3, bitrate=1_000_000)
            await other.open()
            try:
                assert other._bus is link._bus  # one python-can bus, one receive thread
                await other.write_mv(21.0)
                assert await until(lambda: plc.hv == 21.0)
                await new_frames(link, node)
                assert (await other.read_sample()).pv == (await link.read_sample()).pv == f32(plc.pv)
                with pytest.raises(LinkError, match=r"open with defaults by other loops; this link asks for "
                                                    r"\{'bitrate': 1000000\}"):
                    await faster.open()
                bus = link._bus
                await other.close()
                await new_frames(link, node)  # the first link still receives
                assert link._bus is bus and not bus._is_shutdown and await link.read_pv() == f32(plc.pv)
            finally:
                await other.close()
                await faster.close()
            await link.close()
            assert bus._is_shutdown  # the last link's close released the interface
            await link.open()
            assert link._bus is not bus
    arun(main())


def test_writes_reach_the_plc():
    async def main():
        async with rig() as (plc, node, link):
            await link.write_mode(Mode.MAN)
            await link.write_mv(37.25)
            await link._send((CMD_SP, {"SP": 61.5}))  # an HMI's set point: the autotuner sends none
            assert await until(lambda: plc.sp == 61.5)  # frames from one sender arrive in order
            assert plc.mode is Mode.MAN and plc.hv == 37.25 and plc.sp == 61.5
            await link.write_mode(Mode.AUTO)
            assert await until(lambda: plc.mode is Mode.AUTO)
            with pytest.raises(LinkError):
                await link.write_mv(math.nan)
    arun(main())


def test_the_watchdog_frames_arm_the_node_and_a_silent_heartbeat_makes_it_fall_back():
    async def main():
        async with rig() as (plc, node, link):
            await link.write_mode(Mode.MAN)
            await link.write_mv(70.0)
            await link.write_heartbeat(1)
            await link.write_watchdog(Watchdog(timeout=0.5, mv=50.0, mode=Mode.AUTO))  # WdTime: 0.1 s steps
            assert await until(lambda: plc.watchdog.timeout > 0.0 and plc.heartbeat == 1)
            assert plc.watchdog == Watchdog(timeout=0.5, mv=50.0, mode=Mode.AUTO)
            assert 0.5 / plc.ts < 100
            for _ in range(200):
                plc.tick()
                if plc.fallbacks:
                    break
            assert plc.fallbacks == 1 and plc.mode is Mode.AUTO and plc.flags.ite == 22.0
    arun(main())


def test_write_gains_with_no_integral_action_and_read_state():
    async def main():
        async with rig() as (plc, node, link):
            g = Gains(k=2.5, ti=math.inf, td=0.75, nd=5.0, b=0.5, c=0.25)
            await link.write_gains(g)
            assert await until(lambda: plc.gains == g)
            plc.mode = Mode.MAN
            plc.hv = 42.0
            plc.tick()
            await new_frames(link, node)  # frames encoded before the tick (still in flight) would show AUTO
            state = await link.read_state()
            assert state.mode is Mode.MAN
            assert state.mv == f32(plc.mv) and state.sp == f32(plc.sp)
            assert state.gains == g  # all exactly representable in float32; ti = inf travels as Ti = 0
            g2 = Gains(k=0.3, ti=1.7)
            await link.write_gains(g2)
            assert await until(lambda: plc.gains == Gains(k=f32(0.3), ti=f32(1.7)))
    arun(main())


def test_read_state_never_takes_a_frame_sent_before_the_call():
    """Frames still on their way when read_state is called show the state before it: they are not fresh.

    The link dates a frame by its time on the bus (the interface's timestamp), not by when the event loop got to
    it: under load a backlog of frames sent before a change reaches the link after it (the race that failed these
    tests under two CPU burners), and a real CAN network queues frames the same way. Here the backlog is made on
    purpose and the node's answer to AT_Request is held until the link has taken the whole backlog in.
    """
    async def main():
        async with rig() as (plc, node, link):
            await link.read_state()
            node._task.cancel()  # no cyclic frames: only this test's travel
            requests: list[dict] = []
            apply = node._apply
            node._apply = lambda name, v: requests.append(v) if name == "AT_Request" else apply(name, v)
            received = link.stats["frames"]
            for _ in range(3):  # whole cycles sent now, not yet handed to the link (this code holds the loop)
                node.publish(gains=True)
            plc.mode = Mode.MAN
            plc.hv = 42.0
            plc.tick()
            reading = asyncio.ensure_future(link.read_state())
            assert await until(lambda: requests and link.stats["frames"] >= received + 18)
            assert not reading.done()  # it waits for frames sent after the call
            node.publish(gains=True)  # the node's answer
            state = await reading
            assert state.mode is Mode.MAN and state.mv == 42.0
    arun(main())


def test_flags():
    async def main():
        async with rig() as (plc, node, link):
            plc.flags = TuneFlags(tune=True, tbrk=False)
            await new_frames(link, node)
            assert await link.read_flags() == TuneFlags(tune=True)
            await link.write_flags(TuneFlags(tune=False, tbrk=True, tbsy=True, te=False, ite=12.5))
            assert await until(lambda: plc.flags.tbsy)
            # TUNE and TBRK are the PLC's own inputs: the write leaves them alone
            assert plc.flags == TuneFlags(tune=True, tbrk=False, tbsy=True, te=False, ite=12.5)
            await new_frames(link, node)
            assert await link.read_flags() == plc.flags
            plc.flags = TuneFlags(tbrk=True, te=True, ite=3.0)
            await new_frames(link, node)
            assert await link.read_flags() == TuneFlags(tbrk=True, te=True, ite=3.0)
    arun(main())


def test_nan_pv_is_a_link_error():
    async def main():
        async with rig() as (plc, node, link):
            await link.read_pv()
            plc.nan_pv = True
            await new_frames(link, node)
            with pytest.raises(LinkError, match="PV is not a number"):
                await link.read_pv()
            plc.nan_pv = False
            for _ in range(20):  # a NaN frame may still be on its way
                await new_frames(link, node)
                try:
                    value = await link.read_pv()
                    break
                except LinkError:
                    continue
            assert value == f32(plc.pv)
    arun(main())


# Longest a read may take before the test calls it a hang, wall seconds. Not the link's bound (0.2-0.3 s, named in its
# error): on a loaded 2-core machine the event loop itself may run that late, so these tests check what the link
# does — it refuses a stale PV and says within what bound — and only that it does not hang.
HANG = 15.0


@pytest.mark.parametrize("stale_after", [None, 0.05])
def test_silent_node_makes_the_pv_stale_within_the_bound(stale_after):
    async def main():
        timeout = 0.3
        async with rig(timeout=timeout, stale_after=stale_after) as (plc, node, link):
            assert await until(lambda: link.stats["frames"] >= 15)  # five cycles: the PV's period is known
            await link.read_pv()
            node.silent = True
            sent = node.stats["sent"]
            deadline = time.monotonic() + HANG
            with pytest.raises(LinkError, match=rf"stale PV: no fresh AT_Process .*within {timeout:g} s"):
                while time.monotonic() < deadline:  # reads succeed only while the last frame is fresh
                    await link.read_pv()
                    await asyncio.sleep(PERIOD)
            assert node.stats["sent"] == sent  # the node sent nothing meanwhile: the PV was stale, not late
            with pytest.raises(LinkError, match=rf"no fresh .*within {timeout:g} s"):
                await asyncio.wait_for(link.read_state(), HANG)
            # the node still applies commands while silent (a failed transmitter), so a restore works
            await link.write_mv(12.0)
            assert await until(lambda: plc.hv == 12.0)
            node.silent = False
            await new_frames(link, node)
            assert await link.read_pv() == f32(plc.pv)
    arun(main())


def test_no_node_at_all():
    async def main():
        link = CanLink("virtual", f"test-can-{next(_channels)}", timeout=0.2)
        await link.open()
        try:
            with pytest.raises(LinkError, match=r"no fresh AT_Process from the CAN node within 0.2 s \(never received\)"):
                await asyncio.wait_for(link.read_pv(), HANG)
            with pytest.raises(LinkError, match=r"within 0.2 s \(never received\)"):
                await asyncio.wait_for(link.read_flags(), HANG)
        finally:
            await link.close()
    arun(main())


def test_deaf_node_ignores_commands_and_invalid_gains_are_rejected():
    async def main():
        async with rig() as (plc, node, link):
            node.deaf = True
            await link.write_mv(11.0)
            assert await until(lambda: node.stats["ignored"] == 1)
            assert plc.hv != 11.0
            node.deaf = False
            before = plc.gains
            # a negative Ti on the wire is not a gain: the node rejects the apply, the gains stay
            await link._send(("AT_CmdGains1", {"K": 1.0, "Ti": -1.0}), ("AT_CmdGains2", {"Td": 0.0, "N": 10.0}),
                             ("AT_CmdGains3", {"B": 1.0, "C": 0.0}), ("AT_CmdGainsApply", {"Apply": 1}))
            assert await until(lambda: node.stats["rejected"] == 1)
            assert plc.gains == before
    arun(main())


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_bus_failure_is_a_link_error():
    async def main():
        async with rig() as (plc, node, link):
            await link.read_pv()
            link._bus.shutdown()  # the interface goes away under the link
            with pytest.raises(LinkError, match="CAN"):
                await link.write_mv(1.0)
            # the receive thread notices at its next poll; until then the last PV may still be fresh
            deadline = time.monotonic() + 30.0  # generous: the loop ends at the error
            with pytest.raises(LinkError, match="CAN bus error"):
                while time.monotonic() < deadline:
                    await link.read_pv()
                    await asyncio.sleep(PERIOD)
    arun(main())


def test_own_dbc_with_scaled_integer_signals(tmp_path):
    """Another layout (ids, scaled 16-bit PV/MV, big-endian) works as long as the names are the same."""
    text = default_dbc().read_text()
    text = text.replace("BO_ 256 AT_Process: 8 Plc\n SG_ PV : 0|32@1- (1,0) [0|0] \"\" Tuner\n"
                        " SG_ MV : 32|32@1- (1,0) [0|0] \"%\" Tuner",
                        "BO_ 1280 AT_Process: 4 Plc\n SG_ PV : 7|16@0+ (0.01,0) [0|655.35] \"\" Tuner\n"
                        " SG_ MV : 23|16@0+ (0.01,0) [0|655.35] \"%\" Tuner")
    text = text.replace("SIG_VALTYPE_ 256 PV : 1;\nSIG_VALTYPE_ 256 MV : 1;\n", "")
    text = text.replace("CM_ BO_ 256 ", "CM_ BO_ 1280 ")
    own = tmp_path / "own.dbc"
    own.write_text(text)
    db = load_dbc(own)
    assert db.get_message_by_name("AT_Process").frame_id == 0x500
    assert db.encode_message("AT_Process", {"PV": 12.34, "MV": 1.0}) == struct.pack(">HH", 1234, 100)

    async def main():
        async with rig(dbc=own) as (plc, node, link):
            plc.mode = Mode.MAN
            plc.hv = 70.0
            for _ in range(20):
                plc.tick()
            await new_frames(link, node)
            assert await link.read_pv() == pytest.approx(plc.pv, abs=0.006)
            await link.write_mv(55.5)
            assert await until(lambda: plc.hv == 55.5)
    arun(main())


# ------------------------------------------------------- the session over CAN

HIL_SPEED = 10.0


async def tune_over_can(fault=None, fault_after: float = 0.3, handback=None):
    """The real-time session on a simulated plant behind a CAN node, run HIL_SPEED times faster than real time."""
    process = parse_process(PLANT)
    ts = default_sample_time(process)
    plc = SimulatedPlc(process, ts=ts / 2)
    before = (plc.mode, plc.gains)
    channel = f"test-can-{next(_channels)}"
    node = await serve_can(plc, "virtual", channel, period=plc.ts / HIL_SPEED)
    halt = asyncio.Event()
    plant = asyncio.create_task(run(plc, HIL_SPEED, halt))
    link = CanLink("virtual", channel, timeout=0.3)
    await link.open()
    if fault is not None:
        asyncio.get_running_loop().call_later(fault_after, fault, plc, node)
    try:
        # tolerances for a shared CI machine: timing jitter at 10x real time scatters the estimates
        cfg = field_config(RelayConfig(amp=5.0, time_limit=500.0, phase_tol_deg=2.0, gain_tol=0.02))
        result = await tune_link(link, SessionPlan(cfg, ts, speed=HIL_SPEED, handback=handback or HandBack()))
        # the node has taken every command the session sent (a silent node's MV cannot be read back)
        assert await until(lambda: sum(node.stats[k] for k in ("applied", "rejected", "ignored")) >= link.stats["sent"])
    finally:
        halt.set()
        await plant
        await link.close()
        await node.close()
    return result, plc, before


def test_session_over_can_identifies_the_point():
    result, plc, (mode, gains) = arun(tune_over_can(), limit=120.0)  # a hang bound, not a timing requirement
    assert result.ok, result.message
    point = result.identification.point
    s = 1j * point.omega
    true = cmath.exp(-s) / (2 * s + 1)
    # The session measures the process behind the link: the PV frame is the node's latest cyclic one and an MV
    # takes effect at the PLC's next tick, so the loop adds a dead time of at most a session sample plus two PLC
    # ticks (plant seconds). A dead time changes no magnitude and only lags the phase by omega times itself.
    latency = default_sample_time(parse_process(PLANT)) + 2 * plc.ts
    extra_lag = math.degrees(cmath.phase(true) - cmath.phase(point.value))
    assert abs(abs(point.value) / abs(true) - 1) < 0.03
    assert -1.0 < extra_lag < math.degrees(point.omega * latency) + 1.0, (extra_lag, point.omega * latency)
    assert plc.mode is mode and plc.gains == gains


def test_session_over_can_node_goes_silent():
    def silence(plc, node):
        node.silent = True

    result, plc, (mode, gains) = arun(tune_over_can(silence, handback=HandBack(window=1.0, track_timeout=0.3)),
                                      limit=120.0)
    assert result.code is Code.LINK_FAULT, result.message
    # The hand-back writes the saved MV (the silent node still receives) but never AUTO unconfirmed: it cannot read
    # the MV back, so the loop is reported not restored and stays in MAN at the saved MV.
    assert "stale PV" in result.message and "LOOP NOT RESTORED" in result.message
    assert plc.mode is Mode.MAN and plc.hv == 50.0 and plc.gains == gains


def test_session_over_can_nan_pv():
    def nan(plc, node):
        plc.nan_pv = True

    result, plc, (mode, gains) = arun(tune_over_can(nan), limit=120.0)
    assert result.code is Code.LINK_FAULT and "PV is not a number" in result.message, result.message
    assert plc.mode is mode and plc.gains == gains


@pytest.mark.parametrize("bits", [15, 24])
def test_a_short_epoch_reads_back_as_the_epoch_nearest_the_newest(bits):
    """AT_CmdFlags and AT_CmdWatchdog have no room for 32 bits: 1 + epoch mod (2**bits - 1), never 0 (none)."""
    modulus = 2**bits - 1
    for newest in (1, 2, 5, modulus - 1, modulus, modulus + 1, 10 * modulus + 17, 2**32 - 2**16):
        for epoch in (newest - modulus // 2, newest - 3, newest - 1, newest, newest + 1, newest + modulus // 2):
            if epoch < 1:
                continue
            value = epoch_to_wire(epoch, bits)
            assert 1 <= value <= modulus
            # Independently: of the epochs with this residue (every one within a modulus of the newest), the nearest.
            residue = [value - 1 + k * modulus for k in range(newest // modulus - 2, newest // modulus + 3)]
            near = min((e for e in residue if abs(e - newest) <= modulus), key=lambda e: abs(e - newest))
            assert epoch_from_wire(value, bits, newest) == near == epoch, (newest, epoch)
    assert epoch_to_wire(None, bits) == epoch_to_wire(0, bits) == 0 and epoch_from_wire(0, bits, 9) == 0
    assert epoch_to_wire(70000, 32) == epoch_from_wire(70000, 32, 5) == 70000  # a full signal: the epoch itself


def superseded_frames(epoch: int) -> list[can.Message]:
    """Every command frame that moves the loop, as a daemon of lease ``epoch`` sends them, packed by hand per
    docs/can.md: MV 22, mode AUTO, TBSY and TE with ite 7, the watchdog disarmed, heartbeat 9, gains K 2, Ti 3."""
    flags = 1 + epoch % (2**24 - 1)  # the short epochs
    watchdog = 1 + epoch % (2**15 - 1)
    frames = [(0x200, struct.pack("<fI", 22.0, epoch)), (0x201, struct.pack("<II", 1, epoch)),
              (0x203, bytes([0b11]) + flags.to_bytes(3, "little") + struct.pack("<f", 7.0)),
              (0x204, struct.pack("<fHH", 30.0, 0, watchdog << 1)), (0x205, struct.pack("<HHI", 9, 0, epoch)),
              (0x210, struct.pack("<ff", 2.0, 3.0)), (0x211, struct.pack("<ff", 0.0, 10.0)),
              (0x212, struct.pack("<ff", 1.0, 0.0)), (0x213, struct.pack("<II", 1, epoch))]
    return [can.Message(arbitration_id=i, data=data, is_extended_id=False) for i, data in frames]


def test_the_node_ignores_every_command_frame_of_an_older_lease_epoch_and_reports_it():
    """The fence of a fleet on CAN (docs/can.md): a frame names no sender, so the node fences by content — every
    command frame that moves the loop whose Epoch is older than the newest it has seen is ignored (the flags and the
    watchdog's too, their short epochs read as the nearest), and reported at once (AT_Fence)."""
    async def main():
        async with rig() as (plc, node, old):
            new = CanLink("virtual", old.channel, timeout=0.3)
            raw = can.Bus(interface="virtual", channel=old.channel)  # frames already on their way from the old owner
            await new.open()
            try:
                assert old.carries_epoch and new.carries_epoch
                old.epoch, new.epoch = 5, 6
                await old.write_mv(11.0)
                await old.write_watchdog(Watchdog(timeout=20.0, mv=50.0, mode=Mode.AUTO))
                await old.write_heartbeat(1)
                assert await until(lambda: plc.heartbeat == 1) and plc.epoch == 5 and plc.watchdog.timeout == 20.0
                await new.write_mode(Mode.MAN)  # the new owner: its epoch is the newest
                await new.write_flags(TuneFlags(tbsy=True, ite=5.0))
                assert await until(lambda: plc.flags.tbsy) and plc.epoch == 6 and plc.mode is Mode.MAN
                reported = node.stats["sent"]
                for frame in superseded_frames(5):
                    raw.send(frame)
                # MV, mode, flags, watchdog, heartbeat and the apply ignored (the staged gains dropped with it).
                assert await until(lambda: plc.fenced == 6) and node.stats["fenced"] == 6
                assert plc.hv == 11.0 and plc.mode is Mode.MAN and plc.heartbeat == 1 and plc.gains.k != 2.0
                assert plc.flags == TuneFlags(tbsy=True, ite=5.0)
                assert plc.watchdog == Watchdog(timeout=20.0, mv=50.0, mode=Mode.AUTO)
                assert node.stats["sent"] >= reported + 6  # a report at once for each
                assert await until(lambda: old.reported_epoch == (6, 6))
            finally:
                raw.shutdown()
                await new.close()
    arun(main())


def test_the_link_whose_node_reports_a_newer_epoch_is_fenced_and_sends_nothing():
    async def main():
        async with rig() as (plc, node, old):
            new = CanLink("virtual", old.channel, timeout=0.3)
            plain = CanLink("virtual", old.channel, timeout=0.3)  # a tuner outside a fleet: Epoch 0, never fenced
            await new.open()
            await plain.open()
            try:
                old.epoch, new.epoch = 5, 6
                await old.write_mv(11.0)
                await new.write_mv(12.0)
                assert await until(lambda: plc.hv == 12.0 and old.reported_epoch is not None
                                   and old.reported_epoch[0] == 6)
                sent = old.stats["sent"]
                writes = [old.write_mv(40.0), old.write_mode(Mode.MAN), old.write_flags(TuneFlags(tbsy=True)),
                          old.write_watchdog(Watchdog(timeout=0.0, mv=0.0)), old.write_heartbeat(3),
                          old.write_gains(Gains(k=2.0, ti=3.0))]
                for write in writes:
                    with pytest.raises(Fenced, match="has seen lease epoch 6, newer than this daemon.s epoch 5"):
                        await write
                assert old.stats["sent"] == sent  # nothing sent
                await old.read_pv()  # reads are not fenced
                await new.write_flags(TuneFlags(te=True, ite=22.0))
                await plain.write_mv(33.0)
                assert await until(lambda: plc.flags.te and plc.hv == 33.0) and plc.fenced == 0
                # A short epoch newer than the newest becomes the newest (a daemon whose first frame is its flags).
                new.epoch = 7
                await new.write_flags(TuneFlags(te=False, ite=0.0))
                assert await until(lambda: plc.epoch == 7) and not plc.flags.te
            finally:
                await new.close()
                await plain.close()
    arun(main())
