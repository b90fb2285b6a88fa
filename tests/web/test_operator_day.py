"""The operator's day from the dashboard (issue 29), in real chromium, through a real
daemon and the simulated boards: a Z probe on the touch plate."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import playwright.async_api as playwright
import pytest

from hostd.machine import probing
from hostd.sim import SimController
from hostd.sim.probing import TouchPlate
from tests.web.conftest import log_in, running_web, screenshot

pytestmark = pytest.mark.asyncio
expect = playwright.expect

PLATE_TOP = -3.0  # machine Z of the plate's top, 3 mm under the bit where the sim starts


def g2(sim: Any) -> SimController:
    assert isinstance(sim, SimController)
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
