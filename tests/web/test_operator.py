"""The dashboard as an operator's panel (issue 29), in real chromium, through a real daemon
and the simulated boards: home and zero, buttons that follow the state, an override during
a job, arcs, zoom and the side view, keyboard jogging, resume from a line, the console
without status polls, and the page at 1280 and 390 px."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import playwright.async_api as playwright
import pytest

from hostd import daemon
from hostd.sim.grbl import GrblSimController
from tests.daemon.conftest import Rpc, RpcFailure
from tests.sim.grbl.conftest import GrblHost
from tests.web.conftest import Web, log_in, running_web, screenshot

pytestmark = pytest.mark.asyncio(loop_scope="session")  # `browser` (conftest)
expect = playwright.expect

LONG = "".join(f"G1 X{i % 40} Y{(i * 7) % 30} F600\n" for i in range(400))
# Long too, and every line's position known from the file (Z set first): resumable anywhere.
# Its plunge is slow (1.2 s on the simulated board), its feed set before it (a resume there
# goes down at it): a job starts with only the window's four lines on the board, and a
# plunge of 0.12 s ran out before a loaded test machine sent the fifth (CI: the job ended
# `failed`, an underflow after line 4, before its cancel).
DEEP = "G21 G90 F30\nG0 Z5\nG0 X0 Y0\nG1 Z-1\n" + LONG + "G0 Z5\n"
# A full circle (start = end, centre by I J), a half circle by R, and plunges in Z.
ARCS = """G21 G90
G0 X10 Y0 Z5
G1 Z-1 F300
G2 X10 Y0 I-10 J0 F600
G0 Z5
G0 X30 Y0
G1 Z-2 F300
G3 X50 Y0 R10 F600
G0 Z5
"""
PROGRESS_OVER = "(least) => document.getElementById('job-progress').value > least"
GRBL = {"dialect": "grbl"}


async def upload(page: playwright.Page, tmp_path: Path, name: str, text: str) -> None:
    """As an operator does: the file input, Upload; the list then shows it."""
    path = tmp_path / name
    path.write_text(text)
    await page.set_input_files("#upload-file", path)
    await page.click("#upload button")
    await expect(page.locator("#files")).to_have_value(name)
    await expect(page.locator("#analysis")).to_contain_text(f"{name}:")


async def cancel_job(web: Web) -> None:
    """End the test's job at once (its moves would run on for seconds)."""
    rpc = await web.hostd.client()
    await rpc.call("job.cancel", machine="sim1")
    await rpc.close()


async def refused(rpc: Rpc, method: str, **params: Any) -> int:
    """The daemon's error code for a request the page shows as disabled."""
    with pytest.raises(RpcFailure) as failure:
        await rpc.call(method, **params)
    return failure.value.code


async def test_home_zero_and_go_to_zero_from_the_page(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#homed")).to_have_text("no")
        await page.click("#home")
        await expect(page.locator("#homed")).to_have_text("yes")

        rpc = await web.hostd.client()
        await rpc.call("machine.jog", machine="sim1", axes={"x": 12.5, "y": 7.25}, feed=3000)
        await web.hostd.idle(rpc)
        await expect(page.locator("#wx")).to_have_text("12.500")
        await page.click("[data-zero=x]")  # X reads 0 here; the machine did not move
        await expect(page.locator("#wx")).to_have_text("0.000")
        await expect(page.locator("#mx")).to_have_text("12.500")
        await expect(page.locator("#wy")).to_have_text("7.250")
        await page.click("[data-zero=xyz]")
        await expect(page.locator("#wy")).to_have_text("0.000")
        await expect(page.locator("#wz")).to_have_text("0.000")

        await rpc.call("machine.jog", machine="sim1", axes={"x": -2, "y": 3}, feed=3000)
        await web.hostd.idle(rpc)
        await expect(page.locator("#wx")).to_have_text("-2.000")
        await page.click("#goto-zero")  # it moves the machine: asks first
        await page.click("#confirm-yes")
        await expect(page.locator("#wx")).to_have_text("0.000")
        await expect(page.locator("#wy")).to_have_text("0.000")
        await expect(page.locator("#mx")).to_have_text("12.500")
        await rpc.close()


async def test_each_button_is_enabled_only_where_the_daemon_accepts_it(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    moves = ["#home", "[data-zero=x]", "#goto-zero", "#probe", "[data-spindle=cw]"]
    jogs = ["[data-jog=X][data-dir='1']", "[data-jog=Z][data-dir='-1']"]
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        rpc = await web.hostd.client()
        await upload(page, tmp_path, "long.nc", LONG)
        # Idle: moves, jogs and Start; nothing to cancel, clear or resume.
        for selector in [*moves, *jogs, "#start", "#frame", "[data-action=hold]"]:
            await expect(page.locator(selector)).to_be_enabled()
        for action in ("cancel", "clear", "resume"):
            await expect(page.locator(f"[data-action={action}]")).to_be_disabled()
        await expect(page.locator("#toolchange")).to_be_hidden()

        await page.click("#start")
        await expect(page.locator("#supervisor")).to_have_text("operation")
        for selector in [*moves, *jogs, "#start", "#frame"]:
            await expect(page.locator(selector)).to_be_disabled()
        await expect(page.locator("#home")).to_have_attribute(
            "title", "refused while the machine is operation"
        )
        for action in ("hold", "cancel", "reset"):
            await expect(page.locator(f"[data-action={action}]")).to_be_enabled()
        # What the page disables, the daemon refuses: busy (1003).
        assert await refused(rpc, "machine.home", machine="sim1") == 1003
        assert await refused(rpc, "machine.jog", machine="sim1", axes={"x": 1}, feed=500) == 1003
        await page.click("[data-action=hold]")
        await expect(page.locator("[data-action=resume]")).to_be_enabled()
        await page.click("[data-action=cancel]")
        await page.click("#confirm-yes")
        await expect(page.locator("#supervisor")).to_have_text("idle")
        await expect(page.locator("[data-action=cancel]")).to_be_disabled()

        await rpc.call("machine.alarm", machine="sim1")
        await expect(page.locator("#indicator-text")).to_have_text("ALARM")
        for selector in [*moves, *jogs, "#start", "[data-action=resume]"]:
            await expect(page.locator(selector)).to_be_disabled()
        await expect(page.locator("#home")).to_have_attribute("title", "refused in ALARM: Clear")
        await expect(page.locator("[data-action=clear]")).to_be_enabled()
        # In ALARM the daemon refuses moves with the lockout's code (204).
        assert await refused(rpc, "machine.jog", machine="sim1", axes={"x": 1}, feed=500) == 204
        assert await refused(rpc, "machine.zero", machine="sim1", axes={"x": 0}) == 204
        await page.click("[data-action=clear]")
        await page.click("#confirm-yes")
        await expect(page.locator("#indicator-text")).to_have_text("normal")
        for selector in [*moves, *jogs, "#start"]:
            await expect(page.locator(selector)).to_be_enabled()
        await expect(page.locator("[data-action=clear]")).to_be_disabled()
        await rpc.close()


async def test_an_override_changed_mid_job_shows_what_the_board_reports(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine=GRBL) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "long.nc", LONG)
        await page.click("#start")
        await expect(page.locator("#supervisor")).to_have_text("operation")
        await expect(page.locator("#ov-feed")).to_have_text("100%")
        await page.click("[data-override=feed] [data-step='10']")
        await expect(page.locator("#ov-feed")).to_have_text("110%")
        await page.click("[data-override=spindle] [data-step='-10']")
        await expect(page.locator("#ov-spindle")).to_have_text("90%")
        await page.click("[data-override=rapid] [data-set='50']")
        await expect(page.locator("#ov-rapid")).to_have_text("50%")
        rpc = await web.hostd.client()
        snap = await rpc.call("machine.status", machine="sim1")
        assert snap["overrides"] == {"feed": 110, "spindle": 90, "rapid": 50}
        assert snap["supervisor"] == "operation"  # the job went on
        progress = await page.eval_on_selector("#job-progress", "p => p.value")
        await page.wait_for_function(PROGRESS_OVER, arg=progress)
        await page.click("[data-override=feed] [data-set='100']")
        await expect(page.locator("#ov-feed")).to_have_text("100%")
        await rpc.close()


async def dark_near(page: playwright.Page, x: float, y: float) -> int:
    """The darkest pixel (r + g + b, over white) drawn within 3 px of work point (x, y)."""
    return int(
        await page.evaluate(
            """([x, y]) => {
                const canvas = document.getElementById('preview');
                const ratio = window.devicePixelRatio || 1;
                const [cx, cy] = view.preview.toCanvas(x, y);
                const g = canvas.getContext('2d');
                const d = g.getImageData(Math.round((cx - 3) * ratio), Math.round((cy - 3) * ratio),
                                         Math.round(7 * ratio), Math.round(7 * ratio)).data;
                let darkest = 765;  // each pixel as seen over white
                for (let i = 0; i < d.length; i += 4) {
                    const a = d[i + 3] / 255;
                    darkest = Math.min(darkest, (d[i] + d[i + 1] + d[i + 2]) * a + 765 * (1 - a));
                }
                return darkest;
            }""",
            [x, y],
        )
    )


async def test_the_preview_draws_arcs_zooms_pans_and_shows_z_from_the_side(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "arcs.nc", ARCS)
        await expect(page.locator("#analysis")).not_to_contain_text("analysing")
        await expect(page.locator("#analysis")).to_contain_text("Y -10.0…10.0")  # the daemon's
        bounds = await page.evaluate("view.program.bounds")
        # The full circle is whole (as chords it was a point) and the R arc bulges to Y -10.
        assert bounds["lo"] == pytest.approx([-10, -10, -2], abs=0.01)  # drawn in 3° steps
        assert bounds["hi"] == pytest.approx([50, 10, 5], abs=0.01)
        stroke = 450  # r+g+b: the path's grey is darker (289), the grid (560, 700) lighter
        for x, y in ((0, 10), (-10, 0), (0, -10), (40, -10)):  # on the circle, the R arc
            assert await dark_near(page, x, y) < stroke, (x, y)
        assert await dark_near(page, 0, 5) > stroke  # inside the circle: nothing drawn

        scale = await page.evaluate("view.preview.scale")
        await page.click("#zoom-in")
        assert await page.evaluate("view.preview.scale") == pytest.approx(scale * 1.5)
        await page.locator("#preview").scroll_into_view_if_needed()
        box = await page.locator("#preview").bounding_box()
        assert box is not None
        await page.mouse.move(box["x"] + 100, box["y"] + 100)
        await page.mouse.wheel(0, 200)  # down: out, about the cursor
        assert await page.evaluate("view.preview.scale") == pytest.approx(scale * 1.5 * 0.8)
        await page.mouse.down()
        await page.mouse.move(box["x"] + 160, box["y"] + 130)
        await page.mouse.up()
        assert await page.evaluate("[view.preview.panX, view.preview.panY]") != [0, 0]
        assert await dark_near(page, 0, 10) < stroke  # the path moved with the view
        await page.click("#zoom-fit")
        assert await page.evaluate("view.preview.scale") == pytest.approx(scale)

        await page.click("#view-side")  # X across, Z up: the plunges and the cutting depths
        assert await dark_near(page, 0, -1) < stroke  # the circle, seen edge on at Z -1
        assert await dark_near(page, 45, -2) < stroke  # the half circle at Z -2
        assert await dark_near(page, 20, -1.5) > stroke  # between them, at no depth
        await screenshot(page, tmp_path, "preview-side")


# Rows 1 mm apart, each a 10 mm move at file line 1 + 2 * row, joined at alternate ends.
ROWS = "G21 G90 F300\n" + "".join(
    f"G1 X{10 * (row % 2 == 0)} Y{row}\nG1 X{10 * (row % 2)} Y{row}\n" for row in range(1, 61)
)


async def test_the_preview_shows_done_only_what_the_board_ran_not_what_it_planned(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """The preview's green ("done") ends at the line the board says it is running
    (`line_executed`), not at the last line it answered: an answer means the move is in
    the planner, and the planner holds many moves ahead of the tool."""
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "rows.nc", ROWS)
        await page.click("#start")
        # The board runs row 7 or later, and has answered at least twelve lines beyond it.
        await page.wait_for_function(
            """() => {
                const job = view.snapshots.get(view.machine).job;
                return job && job.line_executed >= 15 && job.lines_acked >= job.line_executed + 12;
            }"""
        )
        seen = await page.evaluate(
            """() => {
                const job = view.snapshots.get(view.machine).job;
                drawPreview();  // as the page drew it for this job state, read in the same turn
                const canvas = document.getElementById('preview');
                const ratio = window.devicePixelRatio || 1;
                const g = canvas.getContext('2d');
                const green = (x, y) => {  // the most green-over-red-and-blue within 2 px
                    const [cx, cy] = view.preview.toCanvas(x, y);
                    const [left, top] = [(cx - 2) * ratio, (cy - 2) * ratio].map(Math.round);
                    const side = Math.round(5 * ratio);
                    const d = g.getImageData(left, top, side, side).data;
                    let most = -255;
                    for (let i = 0; i < d.length; i += 4) {
                        if (d[i + 3] < 128) continue;
                        most = Math.max(most, d[i + 1] - Math.max(d[i], d[i + 2]));
                    }
                    return most;
                };
                const rows = [];
                for (let row = 1; row <= 60; row += 1) rows.push([1 + 2 * row, green(5, row)]);
                return { executed: job.line_executed, acked: job.lines_acked, rows };
            }"""
        )
        executed, acked = seen["executed"], seen["acked"]  # every line of ROWS is sendable
        # The job card says where the board is: the line it runs, not the last it answered.
        shown, running, answered = await page.evaluate(
            """() => { const job = view.snapshots.get(view.machine).job;
                       return [document.getElementById('job-at').textContent,
                               job.line_executed, job.lines_acked]; }"""
        )
        assert shown == str(running) and running < answered, (shown, running, answered)
        ran = [green for line, green in seen["rows"] if line < executed - 4]
        planned = [green for line, green in seen["rows"] if executed + 4 < line <= acked]
        assert ran and planned, seen
        assert all(green > 40 for green in ran), seen  # --done, #1a7f37: 72 over red and blue
        assert all(green < 10 for green in planned), seen  # --left, grey: none
        await cancel_job(web)


async def test_the_preview_numbers_lines_as_the_daemon_does_whatever_ends_them(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """A lone CR ends a line for the daemon (Python's universal newlines), so it does for
    the preview: its moves carry the file lines `line_executed` names."""
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "cr.nc", "G21 G90\rG1 X10 F300\r\nG1 Y5\n(done)\rG1 X20\r")
        assert await page.evaluate("view.program.moves.map((m) => m.line)") == [2, 3, 5]
        assert await page.evaluate("view.program.bounds.hi[0]") == 20


async def test_a_job_whose_lines_are_all_answered_is_finishing_not_at_zero_seconds(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """Three long moves: all answered at once, the board runs them for seconds. The ETA
    says so ("finishing"); left to its count of lines it said "0 s"."""
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "long-moves.nc", "G1 X300 F300\nG1 X0\nG1 X300\n")
        await page.click("#start")
        await expect(page.locator("#job-lines")).to_have_text("3 / 3")
        await expect(page.locator("#job-eta")).to_have_text("finishing")
        await expect(page.locator("#supervisor")).to_have_text("operation")  # still moving
        # The bar is full (lines answered) but pulses: not done.
        await expect(page.locator("#job-progress")).to_have_class("finishing")
        await cancel_job(web)
        await expect(page.locator("#job-progress")).not_to_have_class("finishing")


async def test_the_preview_shows_the_selected_file_while_a_job_runs_another(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await upload(page, tmp_path, "long.nc", LONG)
        await page.click("#start")
        await expect(page.locator("#supervisor")).to_have_text("operation")
        await upload(page, tmp_path, "arcs.nc", ARCS)
        progress = await page.eval_on_selector("#job-progress", "p => p.value")
        await page.wait_for_function(PROGRESS_OVER, arg=progress)  # job news came meanwhile
        assert await page.evaluate("view.program.name") == "arcs.nc"
        await expect(page.locator("#analysis")).to_contain_text("arcs.nc:")
        await expect(page.locator("#files")).to_have_value("arcs.nc")


async def test_keyboard_jogging_moves_the_machine_and_stops(
    browser: playwright.BrowserContext, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A board at real speed (the tests' run ten times faster): a held key's jog takes its
    # full 5 s to end by itself, so one that ends sooner was stopped by the page.
    monkeypatch.setattr(daemon, "SIM_SPEED", 1.0)
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        rpc = await web.hostd.client()
        await page.click("h1")  # the page has the focus, no field has it
        await page.keyboard.press("ArrowRight")
        await expect(page.locator("#wx")).to_have_text("1.000")
        await expect(page.locator("#supervisor")).to_have_text("idle")
        await page.focus("#send-line")  # typing: the arrows are the field's
        await page.keyboard.press("ArrowLeft")
        await page.click("h1")
        await page.keyboard.press("PageUp")
        await expect(page.locator("#wz")).to_have_text("1.000")
        await expect(page.locator("#supervisor")).to_have_text("idle")
        await expect(page.locator("#wx")).to_have_text("1.000")  # ArrowLeft in the field: no jog
        assert [job["kind"] for job in await rpc.call("job.list", machine="sim1")] == ["jog"] * 2

        # Held: it moves while the key is down and stops at its release, well short of the
        # 5 s a held key's jog is bounded to (1000 mm/min: 83 mm).
        await page.select_option("#jog-step", "hold")
        await page.keyboard.down("ArrowUp")
        await page.wait_for_function(
            "() => parseFloat(document.getElementById('wy').textContent) > 2"
        )
        await page.keyboard.up("ArrowUp")
        await expect(page.locator("#supervisor")).to_have_text("idle")
        await web.hostd.idle(rpc)
        stopped = (await rpc.call("machine.status", machine="sim1"))["work_position"]["y"]
        assert 2 < stopped < 80
        await expect(page.locator("#wy")).to_have_text(f"{stopped:.3f}")  # and it stays there

        # The window losing the focus stops it too, whatever the key does.
        await page.keyboard.down("ArrowRight")
        await page.wait_for_function(
            "() => parseFloat(document.getElementById('wx').textContent) > 3"
        )
        await page.evaluate("window.dispatchEvent(new Event('blur'))")
        await expect(page.locator("#supervisor")).to_have_text("idle")
        await web.hostd.idle(rpc)
        stopped = (await rpc.call("machine.status", machine="sim1"))["work_position"]["x"]
        assert 3 < stopped < 80
        await expect(page.locator("#wx")).to_have_text(f"{stopped:.3f}")
        await page.keyboard.up("ArrowRight")
        await rpc.close()


async def test_resume_from_a_line_shows_the_plan_of_the_cli_then_starts_there(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    program = "G21 G90\nG0 Z5\nG0 X10 Y10\nG1 Z-1 F300\nG1 X20 F600\nG1 Y20\nG0 Z5\n"
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        rpc = await web.hostd.client()
        # Homed first, as an operator does: a resume climbs to the Z travel's top, which
        # is a place only on a homed machine (this one has no safe_z). Homed, the travel
        # check runs: the work's Z zero is put mid-travel, where the file's Z-1 fits.
        await page.click("#home")
        await expect(page.locator("#homed")).to_have_text("yes")
        await rpc.call("machine.send", machine="sim1", line="G10 L2 P1 X10 Y10 Z50")
        await upload(page, tmp_path, "pocket.nc", program)
        await page.fill("#from-line-number", "5")
        await page.click("#from-line button")
        await expect(page.locator("#plan")).to_be_visible()
        plan = await rpc.call("job.recovery", machine="sim1", file="pocket.nc", line=5)
        await expect(page.locator("#plan-title")).to_have_text("Resume pocket.nc from line 5")
        shown = await page.locator("#plan-preamble").inner_text()
        assert shown.splitlines() == plan["preamble"] + plan.get("approach", [])
        uncertain = await page.locator("#plan-uncertain li").all_inner_texts()
        assert uncertain == (plan["uncertain"] or ["nothing"])
        await page.click("#plan-start")
        await expect(page.locator("#job-title")).to_contain_text("pocket.nc")
        await web.hostd.idle(rpc)
        job = (await rpc.call("job.list", machine="sim1"))[0]
        assert job["start_line"] == 5
        assert job["state"] == "completed"

        # A cancelled job's row offers its own resume: job.recovery {job}, the same plan.
        await upload(page, tmp_path, "deep.nc", DEEP)
        await page.click("#start")
        # The bar still shows the last job's progress until this one's first report.
        await expect(page.locator("#job-title")).to_contain_text("deep.nc · running")
        await page.wait_for_function(PROGRESS_OVER, arg=0.05)
        # And the board past line 3 (its `G0 X0 Y0`): a resume needs X and Y set before
        # its line. The bar counts lines answered, which run ahead of the board's.
        await rpc.call("subscribe", topics=["job"], machine="sim1")
        if ((await rpc.call("job.list", machine="sim1"))[0]["line_executed"] or 0) < 4:
            await rpc.notification(
                lambda n: n["method"] == "job" and (n["params"]["job"]["line_executed"] or 0) >= 4,
                30,
            )
        await page.click("[data-action=cancel]")
        await page.click("#confirm-yes")
        await expect(page.locator("#history tbody tr").first).to_contain_text("cancelled")
        cancelled = (await rpc.call("job.list", machine="sim1"))[0]
        plan = await rpc.call("job.recovery", job=cancelled["id"])
        await page.locator("#history tbody tr").first.get_by_role("button").click()
        await expect(page.locator("#plan-title")).to_have_text(
            f"Resume deep.nc from line {plan['line']}"
        )
        shown = await page.locator("#plan-preamble").inner_text()
        assert shown.splitlines() == plan["preamble"] + plan.get("approach", [])
        await screenshot(page, tmp_path, "resume")
        await page.click("#plan button[value=no]")  # Back: nothing starts
        await expect(page.locator("#plan")).to_be_hidden()
        assert (await rpc.call("job.list", machine="sim1"))[0]["id"] == cancelled["id"]

        # Another program uploaded under the job's name: its row's resume is refused, and
        # the operator is told why, rather than shown a plan of the other program.
        await rpc.call("file.upload", name="deep.nc", data=DEEP.replace("Z-1", "Z-3"))
        await page.locator("#history tbody tr").first.get_by_role("button").click()
        await expect(page.locator("#toast")).to_contain_text(
            f"deep.nc is not the file job {cancelled['id']} ran: it changed since"
        )
        await expect(page.locator("#plan")).to_be_hidden()
        await rpc.close()


async def typed(page: playwright.Page, line: str, shown: str) -> None:
    """The operator sends `line` from the console's field; until the console shows `shown`."""
    await page.fill("#send-line", line)
    await page.click("#send button")
    await expect(page.locator("#console")).to_contain_text(shown)


async def test_the_laser_console_leaves_out_the_status_polls(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine=GRBL) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#console-hidden")).to_contain_text("hidden")
        # The box's example is grbl's, not g2core's JSON.
        example = re.compile(r"e\.g\. \$G or")
        await expect(page.locator("#send-line")).to_have_attribute("placeholder", example)
        for line, shown in (("G0 X1", "← ok"), ("$G", "← [GC:"), ("G4 P0", "→ G4 P0")):
            # After `G0 X1`'s `ok` the daemon polls grbl's modes, `$G`; the board answers
            # in order, so once `G4 P0` is shown every line before it is too.
            await typed(page, line, shown)
        text = await page.locator("#console").inner_text()
        assert "<Idle" not in text
        assert "→ ?" not in text.splitlines()
        before = text.splitlines()[: text.splitlines().index("→ G4 P0")]
        # Only the operator's own `$G` and its answer: not the daemon's poll.
        assert before.count("→ $G") == 1, text
        assert sum(line.startswith("← [GC:") for line in before) == 1, text
        # The board's lines, and nothing the board did not print: the answers' `ok`s and
        # `[GC:...]` are above, not again as the API's JSON.
        assert not [line for line in text.splitlines() if "{" in line], text
        await screenshot(page, tmp_path, "console-laser")
        await page.check("#console-polls")  # asked for: shown
        await expect(page.locator("#console")).to_contain_text("<Idle")


async def test_the_laser_console_leaves_out_a_jobs_own_lines_and_their_oks(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    # The page subscribes with job_lines false: a raster's lines, 1,000 a second and an
    # `ok` each, are not an operator's console; the job row shows the progress.
    moves = [f"G1 X{i}.5 Y{i % 4} F600" for i in range(1, 21)]
    async with running_web(tmp_path, machine=GRBL) as web:
        rpc = await web.hostd.client()
        # The page opens once the daemon's handshake is over: a console opened during it
        # shows the `ok` of a handshake line written before it listened (rightly: it
        # listens from then on), which the count of `ok`s below would take for a job's.
        await web.hostd.idle(rpc)
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#console-hidden")).to_contain_text("hidden")
        await rpc.call("subscribe", topics=["job"], machine="sim1")
        await rpc.call("file.upload", name="raster.nc", data="G21 G90\n" + "\n".join(moves))
        started = await rpc.call("job.start", machine="sim1", file="raster.nc")
        end = await rpc.notification(
            lambda n: (
                n["params"]["job"]["id"] == started["job"]
                and n["params"]["job"]["state"] not in ("running", "paused")
            )
        )
        assert end["params"]["job"]["state"] == "completed"
        await expect(page.locator("#history tbody tr").first).to_contain_text("completed")
        await typed(page, "$G", "→ $G")  # the operator's own line, and its answer
        await expect(page.locator("#console")).to_contain_text("← [GC:")
        await expect(page.locator("#console")).to_contain_text("← ok")
        lines = (await page.locator("#console").inner_text()).splitlines()
        sent = [line for line in lines if line[:1] == "→"]
        assert not [line for line in sent if "G1 X" in line or "G21 G90" in line]
        # Each `ok` shown answers a line shown: none of the job's 21 is there.
        assert sum(line == "← ok" for line in lines) <= len(sent)

        # Asked for (the "job lines" box), the next job's lines are shown, with their oks.
        await page.check("#console-job")
        await expect(page.locator("#console-job")).to_have_attribute("data-subscribed", "true")
        again = await rpc.call("job.start", machine="sim1", file="raster.nc")
        await rpc.notification(
            lambda n: (
                n["params"]["job"]["id"] == again["job"]
                and n["params"]["job"]["state"] == "completed"
            )
        )
        # As written: grbl's default build keeps no line number, so none is sent.
        await expect(page.locator("#console")).to_contain_text(f"→ {moves[-1]}")
        await expect(page.locator("#console")).to_contain_text("← ok")
        await rpc.close()


async def test_the_position_fits_at_1280_and_the_panel_at_390(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    overflow = """() => [...document.querySelectorAll('.pos td')].filter(
        (td) => td.scrollWidth > td.clientWidth
            || td.getBoundingClientRect().right > td.closest('.card').getBoundingClientRect().right
    ).map((td) => td.id)"""
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        rpc = await web.hostd.client()
        # The widest a work position reads: nine characters.
        await rpc.call("machine.zero", machine="sim1", axes={"x": -1234.567, "z": -1234.567})
        await expect(page.locator("#wz")).to_have_text("-1234.567")
        assert await page.evaluate(overflow) == []

        await upload(page, tmp_path, "arcs.nc", ARCS)
        await expect(page.locator("#analysis")).not_to_contain_text("analysing")
        await screenshot(page, tmp_path, "operator")
        await page.set_viewport_size({"width": 390, "height": 844})
        assert await page.evaluate("document.documentElement.scrollWidth") <= 390
        assert await page.evaluate(overflow) == []
        outside = await page.evaluate(
            """() => [...document.querySelectorAll('button, input, select')].filter((el) => {
                const r = el.getBoundingClientRect();
                return r.width > 0 && (r.left < 0 || r.right > 390);
            }).map((el) => el.id || el.textContent)"""
        )
        assert outside == []
        await page.click("[data-jog=X][data-dir='1']")  # the pad works on a phone
        await expect(page.locator("#mx")).to_have_text("1.000")
        await screenshot(page, tmp_path, "phone")
        await rpc.close()


async def test_grbls_door_and_hard_limit_are_shown_with_the_way_out_and_ended_from_the_page(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    async with running_web(tmp_path, machine=GRBL) as web:
        sim = web.hostd.daemon.sims["sim1"]
        page = await browser.new_page()
        await log_in(page, web)
        sim.door(True)  # the door opens: INTERLOCK, moves refused, Resume is the way out
        await expect(page.locator("#indicator-text")).to_have_text("INTERLOCK")
        await expect(page.locator("#lockout-clear")).to_have_text(
            "To end it: close the door, then Resume"
        )
        await expect(page.locator("#home")).to_be_disabled()
        await expect(page.locator("[data-jog=X][data-dir='1']")).to_be_disabled()
        sim.door(False)
        await page.click("[data-action=resume]")
        await expect(page.locator("#indicator-text")).to_have_text("normal")
        await expect(page.locator("#home")).to_be_enabled()

        rpc = await web.hostd.client()
        await rpc.call("settings.set", machine="sim1", values={"21": 1})  # hard limits on
        await web.hostd.idle(rpc)
        await rpc.close()
        sim.limit_switch("x")  # a hard limit: grbl wants a reset before its unlock
        await expect(page.locator("#indicator-text")).to_have_text("ALARM")
        await expect(page.locator("#lockout-message")).not_to_be_empty()
        await expect(page.locator("#lockout-clear")).to_have_text("To end it: Reset, then Clear")
        await expect(page.locator("[data-action=reset]")).to_have_class("danger needed")
        await expect(page.locator("[data-action=clear]")).to_have_class("needed")
        sim.limit_switch("x", active=False)
        await page.click("[data-action=reset]")
        await page.click("#confirm-yes")
        await expect(page.locator("#lockout-clear")).to_have_text("To end it: Clear")
        await page.click("[data-action=clear]")
        await page.click("#confirm-yes")
        await expect(page.locator("#indicator-text")).to_have_text("normal")
        await expect(page.locator("[data-action=clear]")).to_be_disabled()


async def test_grbl_homes_out_of_an_alarm_from_the_page_where_its_firmware_allows(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """grbl takes `$H` in ALARM (system.c) on a machine that homes ($22): after a hard
    limit's reset, Home is enabled and ends the ALARM; before the reset it is not."""
    async with running_web(tmp_path, machine=GRBL) as web:
        sim = web.hostd.daemon.sims["sim1"]
        page = await browser.new_page()
        await log_in(page, web)
        rpc = await web.hostd.client()
        await rpc.call("settings.set", machine="sim1", values={"21": 1, "22": 1})
        await rpc.call("settings.get", machine="sim1", keys=["22"])  # `$$`: read again
        await web.hostd.idle(rpc)
        await expect(page.locator("#homed")).not_to_have_text("yes")
        sim.limit_switch("x")  # a hard limit: the board reads nothing until a reset
        await expect(page.locator("#lockout-clear")).to_have_text(
            "To end it: Reset, then Clear or Home"
        )
        await expect(page.locator("#home")).to_be_disabled()
        await expect(page.locator("#home")).to_have_attribute(
            "title", "refused in ALARM: Reset, then Clear or Home"
        )
        assert await refused(rpc, "machine.home", machine="sim1") == 204
        sim.limit_switch("x", active=False)
        await page.click("[data-action=reset]")
        await page.click("#confirm-yes")
        await expect(page.locator("#lockout-clear")).to_have_text("To end it: Clear or Home")
        await expect(page.locator("#home")).to_be_enabled()
        for selector in ("[data-zero=x]", "#goto-zero", "[data-jog=X][data-dir='1']"):
            await expect(page.locator(selector)).to_be_disabled()  # moves stay refused
        await screenshot(page, tmp_path, "alarm-home")
        await page.click("#home")
        await expect(page.locator("#homed")).to_have_text("yes")
        await expect(page.locator("#indicator-text")).to_have_text("normal")
        await expect(page.locator("[data-zero=x]")).to_be_enabled()
        await rpc.close()


async def test_a_g2core_spindle_started_from_the_page_shows_as_it_runs(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """g2core's spindle, read from the keys the board has (docs/protocol.md, "The
    spindle's keys"): before, the panel said "–" on every g2core whatever it ran."""
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#spindle")).to_have_text("off · S0")
        await page.fill("#spindle-speed", "12000")
        await page.click("[data-spindle=ccw]")
        await expect(page.locator("#spindle")).to_have_text("ccw · S12000")
        await screenshot(page, tmp_path, "g2core-spindle")
        await page.click("[data-spindle=off]")
        await expect(page.locator("#spindle")).to_have_text("off · S12000")


async def test_a_status_poll_typed_while_status_reports_are_off_shows_its_answer(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """g2core: `{sr:n}` and its answer are status traffic, which the console leaves out
    unless *status reports* is ticked; the operator who typed it still sees the report,
    once, as the daemon's answer (`=`), not as a line the board printed."""
    async with running_web(tmp_path) as web:
        page = await browser.new_page()
        await log_in(page, web)
        await expect(page.locator("#console-hidden")).to_contain_text("hidden")
        await typed(page, "{sr:n}", '= {"sr":{')
        await typed(page, "{fbc:n}", '= {"fbc":')  # not status traffic: the board's line
        lines = (await page.locator("#console").inner_text()).splitlines()
        assert '→ {"fbc":null}' in lines and any(
            line.startswith('← {"r":{"fbc":') for line in lines
        ), lines
        assert not [line for line in lines if line.startswith('← {"status"')], lines
        assert not [line for line in lines if line.startswith(('→ {"sr"', '← {"r":{"sr"'))]


async def let_go_of_the_board(
    web: Web, browser: playwright.BrowserContext
) -> tuple[GrblSimController, playwright.Page, Rpc]:
    """The page open on the grbl machine, which hostd has let go of (machine.disconnect):
    its board on native USB (an open resets none), for another sender to leave busy."""
    sim = web.hostd.daemon.sims["sim1"]
    assert isinstance(sim, GrblSimController)
    page = await browser.new_page()
    await log_in(page, web)
    rpc = await web.hostd.client()
    await web.hostd.idle(rpc)
    await rpc.call("machine.disconnect", machine="sim1")
    sim.flash(replace(sim.config, reset_on_open=False))
    return sim, page, rpc


async def test_a_grbl_board_found_holding_moves_shows_amber_with_reset_as_the_way_out(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """A board another sender left holding moves (here: written to its port while hostd
    let go of it) reads no handshake line: the page says why it is still connecting,
    with Hold and Reset usable, and Reset ends it (docs/dialects.md, "A board busy at
    connect")."""
    async with running_web(tmp_path, machine=GRBL) as web:
        sim, page, rpc = await let_go_of_the_board(web, browser)
        other = GrblHost(sim.path)
        try:
            other.send(b"G1 X150 F100\n")
            await sim.wait_state("Run")
            other.send(b"!")
            await sim.wait_state("Hold:0")
        finally:
            other.close()
        with pytest.raises(RpcFailure, match="busy with moves it was given before"):
            await rpc.call("machine.connect", machine="sim1")
        await expect(page.locator("#indicator-text")).to_have_text("connecting: Hold")
        await expect(page.locator("#indicator")).to_have_attribute("data-level", "warning")
        await expect(page.locator("#lockout-message")).to_contain_text(
            "sim1 is Hold, busy with moves it was given before this connection"
        )
        await expect(page.locator("#lockout-message")).to_contain_text("Reset empties it")
        await expect(page.locator("#supervisor")).to_have_text("disconnected")
        await expect(page.locator("[data-action=reset]")).to_be_enabled()
        await expect(page.locator("[data-action=reset]")).to_have_class("danger needed")
        await expect(page.locator("[data-action=hold]")).to_be_enabled()
        await expect(page.locator("#home")).to_be_disabled()
        await expect(page.locator("[data-action=resume]")).to_be_disabled()
        await screenshot(page, tmp_path, "busy-at-connect")
        await page.click("[data-action=reset]")
        await page.click("#confirm-yes")
        await expect(page.locator("#indicator-text")).to_have_text("normal")
        await expect(page.locator("#lockout")).to_be_hidden()
        await expect(page.locator("#supervisor")).to_have_text("idle")
        assert sim.position["x"] < 150  # the held move was dropped, not run
        await rpc.close()


async def test_a_grbl_board_found_in_door_at_connect_is_resumed_from_the_page(
    browser: playwright.BrowserContext, tmp_path: Path
) -> None:
    """A board whose door was opened while hostd let go of it reads no handshake line
    until the door is closed and it is resumed. The page says so with the way out, and
    its Resume, enabled though the machine is still connecting, ends it."""
    async with running_web(tmp_path, machine=GRBL) as web:
        sim, page, rpc = await let_go_of_the_board(web, browser)
        sim.door(True)
        await sim.wait_state("Door:1")
        with pytest.raises(RpcFailure, match="is in Door"):
            await rpc.call("machine.connect", machine="sim1")
        await expect(page.locator("#indicator-text")).to_have_text("INTERLOCK")
        await expect(page.locator("#lockout-clear")).to_have_text(
            "To end it: close the door, then Resume"
        )
        await expect(page.locator("#lockout-message")).to_contain_text(
            "closed and Resume resumes it (it runs on with any moves it holds; Reset drops them)"
        )
        await expect(page.locator("#supervisor")).to_have_text("disconnected")
        await expect(page.locator("[data-action=resume]")).to_be_enabled()
        await expect(page.locator("#home")).to_be_disabled()
        await screenshot(page, tmp_path, "door-at-connect")
        sim.door(False)
        await page.click("[data-action=resume]")
        await expect(page.locator("#supervisor")).to_have_text("idle")
        await expect(page.locator("#indicator-text")).to_have_text("normal")
        await rpc.close()
