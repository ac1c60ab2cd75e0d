"""The dashboard in headless Debian Chromium, driven by Playwright.

Uses /usr/bin/chromium (Debian's package, never a downloaded browser);
skips with the reason when it is not installed. Saves out/dashboard.png.
"""
import shutil
from pathlib import Path

import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
SCREENSHOT = Path(__file__).resolve().parents[1] / "out" / "dashboard.png"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]

sync_api = pytest.importorskip("playwright.sync_api")
if not Path(CHROMIUM).exists():
    pytest.skip("Debian's chromium is not installed (apt-get install chromium)", allow_module_level=True)


@pytest.fixture(scope="module")
def page(served):
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1300, "height": 760})
        page.goto(served[0])
        yield page
        browser.close()


def taxel_colour(page, sensor, index, cols, cell=44):
    r, c = divmod(index, cols)
    return page.evaluate(
        """([sensor, x, y]) => Array.from(document.querySelector(`section[data-sensor="${sensor}"] canvas.live`)
            .getContext("2d").getImageData(x, y, 1, 1).data).join(",")""",
        [sensor, c * cell + 6, r * cell + cell - 6],
    )


def test_page_loads_with_live_frames_for_every_sensor(page):
    page.wait_for_selector('section[data-sensor="2"][data-frames]', timeout=10_000)
    first = int(page.get_attribute('section[data-sensor="0"]', "data-frames"))
    page.wait_for_timeout(500)
    assert int(page.get_attribute('section[data-sensor="0"]', "data-frames")) > first + 5
    assert page.locator("section.panel").count() == 3
    page.wait_for_function("document.getElementById('link').textContent.startsWith('link up')", timeout=5000)
    page.wait_for_function("/latency p99 \\d+\\.\\d ms/.test(document.getElementById('stats').textContent)", timeout=5000)


def test_heatmap_follows_the_press(page):
    page.wait_for_selector('section[data-sensor="0"][data-frames]', timeout=10_000)
    reds = []
    for _ in range(25):  # the press scene cycles 0 → 5 N → 0 every 2 s
        reds.append(int(taxel_colour(page, 0, 27, 8).split(",")[0]))
        page.wait_for_timeout(100)
    assert max(reds) - min(reds) > 150  # the pressed taxel goes from dark to hot
    untouched = [int(taxel_colour(page, 0, 0, 8).split(",")[0]) for _ in range(3)]
    assert max(untouched) < 20  # a free taxel stays dark (noise is ~0.01 N)


def test_tare_button_tares_and_screenshot_is_saved(page, served):
    _, tares = served
    with page.expect_response("**/tare") as response:
        page.click("#tare")
    assert response.value.status == 200 and tares == [None]
    page.wait_for_timeout(1500)
    SCREENSHOT.parent.mkdir(exist_ok=True)
    page.screenshot(path=str(SCREENSHOT))
    assert SCREENSHOT.stat().st_size > 10_000
