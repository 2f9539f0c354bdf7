"""A loop that could not be handed back, on the operator page (real Chromium): the daemon over an external simulated
PLC on Modbus (the rig of tests/test_handback.py) frozen mid-experiment, so the hand-back fails (code 20, the
status's ``restore``) and is retried; then thawed, so the loop comes back.
"""

from __future__ import annotations

from autotuner.engine.outcome import Code
from helpers import logged_in_page
from test_handback import TOKEN, WAIT, at_relay_level, daemon, plc, wait_for  # noqa: F401 (plc: the fixture)


def test_a_loop_not_handed_back_is_shown_as_loop_not_restored_until_it_is_back(tmp_path, plc):  # noqa: F811
    with (daemon(tmp_path, plc, window=1.0, retry_first=0.3, retry_max=1.0) as d,
          logged_in_page(f"http://127.0.0.1:{d.port}/", TOKEN) as page):
        page.wait_for_selector("#loops tr[data-loop=L1]")
        sid = d.tune()
        at_relay_level(plc)
        plc.freeze()  # the session's hand-back cannot reach the PLC: after its 1 s window, not restored
        status = wait_for(lambda: (s := d.status())["restore"] is not None and s, WAIT, "the loop not restored")
        assert status["ite"] == float(Code.LOOP_NOT_RESTORED) and status["restore"]["session"] == sid

        # The overview: the row in the not-restored state, with the attempts and the error; no success colour.
        row = "#loops tr[data-loop=L1]"
        page.wait_for_selector(f"{row}.st-notrestored .not-restored")
        assert page.inner_text(f"{row} .badge.notrestored") == "LOOP NOT RESTORED"
        box = page.inner_text(f"{row} .not-restored")
        assert "LOOP NOT RESTORED" in box and "attempt" in box and "AUTO at MV 50" in box
        assert status["restore"]["last_error"].split(":")[0] in box
        # The attempts go up on the page as the daemon retries (every ≤ 1 s here).
        page.wait_for_function("(s) => Number(document.querySelector(s)?.dataset.restoreAttempts) >= 3",
                               arg=f"{row} [data-restore-attempts]")
        assert page.locator(f"{row} .badge.ok").count() == 0

        # The loop page: the same, prominently, TUNE and apply disabled, the result card not a success.
        page.click(f"{row} a.loop-id")
        page.wait_for_selector("#status.st-notrestored .not-restored")
        assert page.inner_text("#badge") == "LOOP NOT RESTORED"
        assert "attempts since" in page.inner_text("#status .not-restored")
        assert page.inner_text("#status [data-flag=te]") == "TE 1"
        assert page.inner_text("#status [data-flag=ite]") == f"ite {int(Code.LOOP_NOT_RESTORED)}"
        page.wait_for_selector("#result.failed #why")
        assert page.inner_text("#result #why").startswith("LOOP NOT RESTORED")
        assert page.is_disabled("#tune") and page.is_disabled("#apply")
        assert page.locator(".badge.ok, .progress, #result #applied").count() == 0

        # The PLC answers again: the daemon hands the loop back, and the page says the loop is no longer
        # "not restored" (the session's own outcome, a link fault, shows instead).
        plc.thaw()
        page.wait_for_selector("#status:not(.st-notrestored)")
        page.wait_for_selector("#status .not-restored", state="detached")
        assert page.inner_text("#badge") == "FAILED"
        assert page.inner_text("#status [data-flag=ite]") == f"ite {int(Code.LINK_FAULT)}"
        page.wait_for_selector("[data-readout=mode]:has-text('AUTO')")
        page.wait_for_function("() => !document.querySelector('#result #why')?.textContent.startsWith('LOOP NOT')"
                               " && document.querySelector('#result #why')")
        assert d.status()["restore"] is None
