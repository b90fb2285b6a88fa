"""The dashboard in a real headless Chromium (Debian's), driven by Playwright.

Playwright never downloads a browser here: it launches /usr/bin/chromium
with a fresh profile (tests/web/conftest.py); a missing binary fails the
test (`.ci/run` installs it). HOSTD_SCREENSHOTS=DIR saves the screenshots
there too (docs/screenshots is where the README's come from).
"""

from __future__ import annotations

import re
from pathlib import Path

import playwright.async_api as playwright
import pytest

from hostd.api.tokens import TokenStore
from tests.web.conftest import log_in, running_web, screenshot
from tests.web.test_operator import upload

SIGNALS = {"coolant_flow_low": {"key": "ain1", "below": 1.0}}
LONG = "".join(f"G1 X{i % 40} Y{(i * 7) % 30} F600\n" for i in range(400))
PROGRESS_OVER = "(least) => document.getElementById('job-progress').value > least"

pytestmark = pytest.mark.asyncio(loop_scope="session")  # `browser` (conftest)


async def test_log_in_upload_start_hold_resume_and_see_a_fault(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    expect = playwright.expect
    async with running_web(tmp_path, machine={"signals": SIGNALS}) as web:
        sim = web.hostd.daemon.sims["sim1"]
        sim.set_analog(1, 3.0)  # coolant flowing
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#controller")).to_have_text("READY")
        await expect(page.locator("#indicator")).to_have_attribute("data-level", "normal")

        program = tmp_path / "star.nc"
        program.write_text(LONG)
        await page.set_input_files("#upload-file", program)
        await page.click("#upload button")
        await expect(page.locator("#files")).to_have_value("star.nc")
        await expect(page.locator("#analysis")).to_contain_text("400 lines")
        await page.click("#start")
        await expect(page.locator("#supervisor")).to_have_text("operation")
        await page.wait_for_function(PROGRESS_OVER, arg=0.02)
        await screenshot(page, tmp_path, "dashboard")

        await page.click("[data-action=hold]")
        await expect(page.locator("#controller")).to_have_text("HOLD")
        held = await page.eval_on_selector("#job-progress", "p => p.value")
        await page.click("[data-action=resume]")
        await expect(page.locator("#controller")).to_have_text("RUN")
        await page.wait_for_function(PROGRESS_OVER, arg=held)

        await page.click("[data-action=cancel]")  # destructive: asks first
        await expect(page.locator("#confirm")).to_be_visible()
        await page.click("#confirm-yes")
        await expect(page.locator("#history tbody tr").first).to_contain_text("cancelled")
        await expect(page.locator("#job-rate")).to_have_text("–")  # a running job's only
        # The job kill, 0x04, is named as g2core names it ("Job killed by ^d"), not a box.
        await expect(page.locator("#console")).to_contain_text("→ ^D\n")
        assert "\x04" not in await page.text_content("#console")
        # The cancelled job's Resume… is inside its card, not scrolled out of it (the
        # start's whole date once pushed it past the edge at 1280 px).
        await expect(page.locator("#history tbody tr button").first).to_have_text("Resume…")
        right, edge = await page.evaluate(  # in one turn: the table is redrawn as news comes
            """() => [document.querySelector('#history tbody tr button'),
                      document.getElementById('history').parentElement]
                     .map((element) => element.getBoundingClientRect().right)"""
        )
        assert right <= edge, (right, edge)

        sim.set_analog(1, 0.2)  # the coolant stops: an alert
        await expect(page.locator("#indicator")).not_to_have_attribute("data-level", "normal")
        await expect(page.locator("#faults")).to_contain_text("water_flow")
        # What moves the machine or powers its spindle is refused while it lasts (1007),
        # as a job and a jog are; setting zero and the spindle's Off are not.
        for powered in ("#home", "#goto-zero", "#probe", "[data-spindle=cw]", "[data-jog]"):
            button = page.locator(powered).first
            await expect(button).to_be_disabled()
            why = re.compile("fault is active: water_flow")
            await expect(button).to_have_attribute("title", why)
        for safe in ("[data-zero=xyz]", "[data-spindle=off]"):
            await expect(page.locator(safe)).to_be_enabled()
        row = page.locator("#faults li", has_text="water_flow")
        await expect(row).to_have_class(re.compile(r"\balert\b"))
        await screenshot(page, tmp_path, "fault")

        # Its way out is on the page: Override, asked first; then its removal.
        await row.get_by_role("button", name="Override").click()
        await expect(page.locator("#confirm")).to_be_visible()
        await page.click("#confirm-yes")
        await expect(row).to_contain_text("(overridden)")
        await expect(row).to_have_class(re.compile(r"\bwarning\b"))
        await expect(page.locator("#home")).to_be_enabled()  # no longer refused for it
        await screenshot(page, tmp_path, "fault-overridden")
        await row.get_by_role("button", name="Remove override").click()
        await expect(row).not_to_contain_text("(overridden)")
        await expect(page.locator("#home")).to_be_disabled()
        # One that software clears has Clear: unparseable output, a lexical fault.
        sim.inject_garbage(b'{"r":{"broken"\n')
        lexical = page.locator("#faults li", has_text="lexical")
        await lexical.get_by_role("button", name="Clear").click()
        await expect(lexical).to_have_count(0)
        await expect(page.locator("#faults li", has_text="water_flow")).to_have_count(1)

        await page.set_viewport_size({"width": 390, "height": 844})
        await screenshot(page, tmp_path, "phone")
        width = await page.evaluate("document.documentElement.scrollWidth")
        assert width <= 390, "the page scrolls sideways on a phone"


async def test_the_csp_blocks_inline_script(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        violated = await page.evaluate(
            """() => new Promise((resolve) => {
                document.addEventListener('securitypolicyviolation',
                    (e) => resolve(e.violatedDirective), {once: true});
                const s = document.createElement('script');
                s.textContent = 'window.inlineRan = true';
                document.body.append(s);
            })"""
        )
        assert violated.startswith("script-src")
        assert await page.evaluate("window.inlineRan === undefined")


async def test_watch_only_shows_the_machine_without_controls(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    expect = playwright.expect
    async with running_web(tmp_path, control=False) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#watch-only")).to_be_visible()
        for control in ("[data-action=hold]", "[data-action=reset]", "#start", "#upload"):
            await expect(page.locator(control)).to_be_hidden()
        hold = "rpc.call('machine.feedhold', {machine: 'sim1'}).catch(e => e.code)"
        assert await page.evaluate(hold) == -32601
        await screenshot(page, tmp_path, "watch-only")


async def test_an_alarm_is_red_with_its_reason_and_is_cleared_from_the_page(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    expect = playwright.expect
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#lockout")).to_be_hidden()
        rpc = await web.hostd.client()
        try:
            await rpc.call("machine.alarm", machine="sim1")
        finally:
            await rpc.close()
        await expect(page.locator("#controller")).to_have_text("ALARM")
        # Not a green "normal": the light is red and names the lockout, its reason and its way out.
        await expect(page.locator("#indicator")).to_have_attribute("data-level", "alert")
        await expect(page.locator("#indicator-text")).to_have_text("ALARM")
        await expect(page.locator("#lockout")).to_be_visible()
        await expect(page.locator("#lockout-message")).not_to_be_empty()
        await expect(page.locator("#lockout-clear")).to_have_text("To end it: Clear")
        await expect(page.locator("[data-action=clear]")).to_have_class("needed")
        await screenshot(page, tmp_path, "alarm")

        await page.click("[data-action=clear]")  # asks first
        await page.click("#confirm-yes")
        await expect(page.locator("#indicator")).to_have_attribute("data-level", "normal")
        await expect(page.locator("#lockout")).to_be_hidden()
        await expect(page.locator("#controller")).not_to_have_text("ALARM")


async def test_the_page_shows_the_analysis_its_warnings_and_the_travel_refusal_before_start(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    expect = playwright.expect
    async with running_web(tmp_path) as web:
        rpc = await web.hostd.client()
        await web.hostd.idle(rpc)
        await rpc.call("machine.send", machine="sim1", line="G28.2 X0 Y0 Z0")
        await web.hostd.idle(rpc)
        assert (await rpc.call("machine.status", machine="sim1"))["homed"] is True
        page = await browser.new_page()
        await log_in(page, web)

        # X to 350 mm: the simulator's travel is 0..300
        await upload(
            page, tmp_path, "wide.nc", "G21 G90\nG1 X350 Y10 F6000\nG38.2 Z-5 F100\nG1 X0\n"
        )

        await expect(page.locator("#travel")).to_be_visible()
        await expect(page.locator("#travel")).to_contain_text("leaves sim1's travel")
        await expect(page.locator("#travel")).to_contain_text("X runs")
        await expect(page.locator("#start")).to_be_disabled()
        await expect(page.locator("#frame")).to_be_disabled()  # its XY box leaves it too
        await expect(page.locator("#frame")).to_have_attribute("title", re.compile("outline"))
        await expect(page.locator("#warnings")).to_contain_text("line 3: G38.2 probing")
        await expect(page.locator("#analysis")).to_contain_text("X 0.0…350.0")
        await expect(page.locator("#analysis")).to_contain_text("about 4 s")  # the daemon's
        await screenshot(page, tmp_path, "travel-refused")
        assert await rpc.call("job.list", machine="sim1") == []  # nothing was started

        # Inside the XY travel, Z below it: framed, not run.
        await upload(page, tmp_path, "deep.nc", "G21 G90\nG1 X150 Y10 F6000\nG1 Z-5 F100\nG1 X0\n")
        await expect(page.locator("#travel")).to_contain_text("Z runs")
        await expect(page.locator("#start")).to_be_disabled()
        await expect(page.locator("#frame")).to_be_enabled()

        await upload(page, tmp_path, "fits.nc", "G21 G90\nG1 X150 F6000\nG1 X0\n")
        await expect(page.locator("#analysis")).to_contain_text("X 0.0…150.0")
        await expect(page.locator("#travel")).to_be_hidden()
        await expect(page.locator("#start")).to_be_enabled()
        await expect(page.locator("#frame")).to_be_enabled()
        await expect(page.locator("#warnings li")).to_have_count(0)
        await rpc.close()


async def test_each_position_column_says_its_own_units_when_the_board_is_in_g20(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """g2core in G20 reports the work position in inches and the machine position in
    mm: one "in" over both columns (as the page had it) misread the machine's."""
    expect = playwright.expect
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#work-units")).to_have_text("mm")
        await expect(page.locator("#machine-units")).to_have_text("mm")
        rpc = await web.hostd.client()
        await expect(page.locator("#jog-units")).to_have_text("mm")
        await rpc.call("machine.send", machine="sim1", line="G20")
        await expect(page.locator("#work-units")).to_have_text("in")
        await expect(page.locator("#machine-units")).to_have_text("mm")
        # A jog is in the units mode: the step and feed say so.
        await expect(page.locator("#jog-units")).to_have_text("in")
        await expect(page.locator("#jog-feed-units")).to_have_text("in/min")
        await rpc.close()


async def test_revoking_the_token_sends_the_open_page_back_to_the_login(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        store = TokenStore(web.hostd.daemon.state_dir)  # as `hostd token revoke` does
        assert store.revoke(store.records()[0].id)
        # Its WebSocket is closed by the daemon; the page finds its session gone.
        await page.wait_for_url(f"{web.url}/login")
        # And the cookie it still holds opens nothing.
        await page.goto(f"{web.url}/")
        await page.wait_for_url(f"{web.url}/login")
