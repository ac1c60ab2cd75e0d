"""The dashboard in headless Debian Chromium, driven by Playwright, against a
live in-process service reading the simulator (press scene, three sensors).

Skips with the reason when Debian's chromium is not installed (tests/chromium.py).
Saves /tmp/dashboard.png.
"""
from pathlib import Path

import pytest

from tests.chromium import VIEWPORT

SCREENSHOT = Path("/tmp/dashboard.png")


def taxel_pixel(page, sensor, index, cols):
    """RGBA at the lower-left inside of a taxel's cell, clear of its number."""
    return page.evaluate(
        """([sensor, index, cols]) => {
            const canvas = document.querySelector(`section[data-sensor="${sensor}"] canvas.live`);
            const cell = canvas.width / cols, r = Math.floor(index / cols), c = index % cols;
            return Array.from(canvas.getContext("2d").getImageData(c * cell + 6, r * cell + cell - 6, 1, 1).data);
        }""",
        [sensor, index, cols],
    )


def panel_order(page):
    return [int(s) for s in page.eval_on_selector_all("section.panel", "els => els.map(e => e.dataset.sensor)")]


@pytest.fixture(scope="module")
def page(served, browser):
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(served[0])
    yield page
    page.close()


def test_page_loads_with_live_frames_for_every_sensor(page):
    page.wait_for_selector('section[data-sensor="2"][data-frames]', timeout=10_000)
    first = int(page.get_attribute('section[data-sensor="0"]', "data-frames"))
    page.wait_for_timeout(500)
    assert int(page.get_attribute('section[data-sensor="0"]', "data-frames")) > first + 5
    assert page.locator("section.panel").count() == 3
    page.wait_for_selector('#status[data-state="ok"]', timeout=5000)
    assert page.text_content("#status").startswith("Live · sim://")
    page.wait_for_function("/latency p99 \\d+\\.\\d ms/.test(document.getElementById('stats').textContent)", timeout=5000)


def test_heatmap_follows_the_press(page):
    page.wait_for_selector('section[data-sensor="0"][data-frames]', timeout=10_000)
    reds = []
    for _ in range(25):  # the press scene cycles 0 → 5 N → 0 every 2 s
        reds.append(taxel_pixel(page, 0, 27, 8)[0])
        page.wait_for_timeout(100)
    assert max(reds) - min(reds) > 150  # the pressed taxel goes from dark to hot
    untouched = [taxel_pixel(page, 0, 0, 8)[0] for _ in range(3)]
    assert max(untouched) < 20  # a free taxel stays dark (noise is ~0.01 N)


def test_panels_are_sorted_by_id_on_every_load(served, browser):
    page = browser.new_page(viewport=VIEWPORT)
    orders = []
    for _ in range(3):
        page.goto(served[0])
        page.wait_for_selector('section[data-sensor="2"][data-frames]', timeout=10_000)
        orders.append(panel_order(page))
    page.close()
    assert orders == [[0, 1, 2]] * 3


def test_panels_share_the_whole_window_width(page):
    page.wait_for_selector('section[data-sensor="2"][data-frames]', timeout=10_000)
    boxes = [page.locator(f'section[data-sensor="{i}"]').bounding_box() for i in range(3)]
    assert len({round(b["y"]) for b in boxes}) == 1  # one row of three at 1400 px
    assert boxes[0]["x"] < 40 and boxes[2]["x"] + boxes[2]["width"] > VIEWPORT["width"] - 40
    assert min(b["width"] for b in boxes) > 380


def test_no_console_errors_and_the_icon_is_served(served, browser):
    page = browser.new_page(viewport=VIEWPORT)
    errors, failed, icons = [], [], []
    page.on("console", lambda m: m.type == "error" and errors.append(m.text))
    page.on("response", lambda r: (failed if r.status >= 400 else icons if "favicon" in r.url else []).append(r.url))
    page.goto(served[0])
    page.wait_for_selector('section[data-sensor="2"][data-frames]', timeout=10_000)
    page.wait_for_timeout(1500)
    page.close()
    assert errors == [] and failed == []
    assert any(url.endswith("/static/favicon.svg") for url in icons)


def test_tare_button_tares_and_screenshot_is_saved(page, served):
    _, tares = served
    with page.expect_response("**/tare") as response:
        page.click("#tare")
    assert response.value.status == 200 and tares == [None]
    page.wait_for_timeout(1500)
    page.screenshot(path=str(SCREENSHOT))
    assert SCREENSHOT.stat().st_size > 10_000
