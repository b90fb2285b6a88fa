"""The operator's day from the dashboard (issue 29), in real chromium, through a real
daemon and the simulated boards: a Z probe on the touch plate, a laser's test fire and
frame, macros, and g2core's overrides."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import playwright.async_api as playwright
import pytest

from hostd.machine import probing
from hostd.sim import SimController
from hostd.sim.grbl.controller import GrblSimController
from hostd.sim.probing import TouchPlate
from tests.web.conftest import log_in, running_web, screenshot
from tests.web.test_operator import ARCS, LONG, PROGRESS_OVER, upload

pytestmark = pytest.mark.asyncio(loop_scope="session")  # `browser` (conftest)
expect = playwright.expect

PLATE_TOP = -3.0  # machine Z of the plate's top, 3 mm under the bit where the sim starts
TWO_TOOLS = "G21 G90\nG0 X0 Y0 Z0\nT1 M6\nG0 X1\nG1 X2 F3000\nT2 M6 (second tool)\nG0 X3\nM2\n"
MACROS = [
    {
        "name": "corner",
        "text": "G21 G90 (to a corner)\nG0 X{x} Y{y}",
        "params": {"x": {"min": 0, "max": 40}, "y": {"min": 0, "max": 40, "default": 3}},
    }
]
LASER = {"dialect": "grbl", "laser": True, "macros": MACROS}


def g2(sim: Any) -> SimController:
    assert isinstance(sim, SimController)
    return sim


def grbl(sim: Any) -> GrblSimController:
    assert isinstance(sim, GrblSimController)
    return sim


async def test_a_z_probe_on_the_touch_plate_from_the_page(
    browser: playwright.BrowserContext, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(probing, "SETTLE", 0.0)  # the pause for the operator's hands
    probe = {"feed": 600.0, "max_travel": 10.0, "retract": 2.0}
    async with running_web(tmp_path, machine={"probe": probe}) as web:
        sim = g2(web.hostd.daemon.sims["sim1"])
        sim.touch_plate(TouchPlate(top=PLATE_TOP))
        page = await browser.new_page()
        await log_in(page, web)
        await page.fill("#probe-plate", "10")
        await page.click("#probe")
        await expect(page.locator("#confirm-text")).to_contain_text("10 mm plate")
        await page.click("#confirm-yes")
        # The daemon waits to see the probe input work: the page says what to do.
        await expect(page.locator("#probe-status")).to_contain_text("Touch the plate to the bit")
        await expect(page.locator("#probe")).to_be_disabled()  # until answered
        await screenshot(page, tmp_path, "probe")
        sim.touch(reads=2)  # the operator touches the plate to the bit, and lets go
        await expect(page.locator("#probe-status")).to_contain_text("work zero set on Z")
        await expect(page.locator("#probe-status")).to_contain_text("Z -3.000")
        # Retracted 2 mm above the plate's top, which is the plate's 10 mm above the work.
        await expect(page.locator("#wz")).to_have_text("12.000")
        await expect(page.locator("#mz")).to_have_text("-1.000")


async def test_a_job_with_an_m6_prompts_is_answered_and_goes_on(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine={"tool_change": "pause"}) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "two.nc", TWO_TOOLS)
        await page.click("#start")
        await expect(page.locator("#toolchange")).to_be_visible()
        await expect(page.locator("#toolchange-text")).to_have_text("Change to tool 1 (line 3)")
        await expect(page.locator("#supervisor")).to_have_text("paused")
        # Meanwhile the operator may jog (the daemon serves it as the job's lines), not
        # resume past the prompt, and a held key's jog is refused: its stop would be.
        await expect(page.locator("[data-action=resume]")).to_be_disabled()
        await expect(page.locator("#jog-stop")).to_be_disabled()
        await page.click("h1")
        await page.keyboard.press("PageUp")
        await expect(page.locator("#wz")).to_have_text("1.000")
        await screenshot(page, tmp_path, "tool-change")
        await page.click("#toolchange-done")
        await expect(page.locator("#toolchange-text")).to_have_text("Change to tool 2 (line 6)")
        await page.click("#toolchange-done")
        await expect(page.locator("#toolchange")).to_be_hidden()
        await expect(page.locator("#history tbody tr").first).to_contain_text("completed")
        rpc = await web.hostd.client()
        job = (await rpc.call("job.list", machine="sim1"))[0]
        assert [(c["tool"], c["line"]) for c in job["tool_changes"]] == [(1, 3), (2, 6)]
        await rpc.close()


async def test_a_laser_test_fire_from_the_page_ends_with_the_beam_off(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine=LASER) as web:
        board = grbl(web.hostd.daemon.sims["sim1"]).board
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#laser-set")).to_be_visible()
        await page.fill("#laser-power", "5")
        await page.fill("#laser-duration", "0.3")
        await page.click("#laser-test")
        await expect(page.locator("#confirm-text")).to_contain_text("5% for 0.3 s")
        await page.click("#confirm-yes")
        await expect(page.locator("#toast")).to_have_text("laser test done")
        powers = [power for _, power in board.beam]
        assert max(powers) == 0.05 * board.settings[30]  # it fired, at 5 %, never more
        assert board.beam_power() == 0.0


async def test_frame_from_the_page_traces_the_selected_files_box(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine=LASER) as web:
        board = grbl(web.hostd.daemon.sims["sim1"]).board
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "arcs.nc", ARCS)
        before = len(board.traversed)
        await page.click("#frame")
        await expect(page.locator("#history tbody tr").first).to_contain_text("completed")
        moves = list(board.traversed)[before:]
        corners = [(round(m.move.target["x"], 3), round(m.move.target["y"], 3)) for m in moves]
        # The box of the circle (X -10..10) and the R arc (to X 50, down to Y -10).
        assert corners[-5:] == [(-10, -10), (50, -10), (50, 10), (-10, 10), (-10, -10)]
        assert not any(m.cutting for m in moves)  # the beam never on


async def test_a_macro_runs_from_the_page_with_its_params(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine=LASER) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#macros-card")).to_be_visible()
        form = page.locator("#macros form").first
        await expect(form).to_contain_text("corner")
        await expect(form.locator("input[name=y]")).to_have_value("3")  # its default
        await form.locator("input[name=x]").fill("12.5")
        await form.locator("button").click()
        await expect(page.locator("#wx")).to_have_text("12.500")
        await expect(page.locator("#wy")).to_have_text("3.000")
        await expect(page.locator("#history tbody tr").first).to_contain_text("completed")


async def test_g2cores_feed_override_changed_mid_job_from_the_page(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#ov-feed")).to_have_text("100%")
        await upload(page, tmp_path, "long.nc", LONG)
        await page.click("#start")
        await expect(page.locator("#supervisor")).to_have_text("operation")
        await page.click("[data-override=feed] [data-step='10']")
        await expect(page.locator("#ov-feed")).to_have_text("110%")
        progress = await page.eval_on_selector("#job-progress", "p => p.value")
        await page.wait_for_function(PROGRESS_OVER, arg=progress)
        rpc = await web.hostd.client()
        assert (await rpc.call("machine.status", machine="sim1"))["overrides"]["feed"] == 110
        await rpc.close()
