"""The dashboard against `tactile` run as a command, in a directory the test
owns: the Record button names the file the service writes, and the end of a
replay is shown, also to a page opened after it. Saves
/tmp/dashboard-replay-finished.png.
"""
import contextlib
import json
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from tests.chromium import VIEWPORT, sync_api
from tests.test_dashboard import taxel_pixel

TACTILE = shutil.which("tactile", path=str(Path(sys.executable).parent)) or shutil.which("tactile")
REPLAY_SCREENSHOT = Path("/tmp/dashboard-replay-finished.png")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get_json(url):
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.load(response)


@contextlib.contextmanager
def tactile(*args, cwd):
    """Base URL of `tactile ARGS --port N` once its /health answers."""
    port = free_port()
    log = open(cwd / "tactile.log", "wb")
    process = subprocess.Popen([TACTILE, *args, "--port", str(port)], cwd=cwd, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/"
    try:
        deadline = time.monotonic() + 15
        while True:
            try:
                get_json(url + "health")
                break
            except OSError:
                assert process.poll() is None and time.monotonic() < deadline, (cwd / "tactile.log").read_text()
                time.sleep(0.1)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()


def test_record_button_shows_the_path_the_service_writes(browser, tmp_path):
    with tactile("serve", "--source", "sim://?scene=press&rate=250", cwd=tmp_path) as url:
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        page.wait_for_selector('#status[data-state="ok"]', timeout=10_000)
        page.click("#record")
        page.wait_for_selector("#record-info:not([hidden])", timeout=5000)
        shown = page.text_content("#record-path")
        status = get_json(url + "record")
        assert status["active"] and shown == status["path"]
        assert page.text_content("#record-label").startswith("● Recording")
        written = tmp_path / shown  # an absolute path stays itself; a service that predates names writes in its cwd
        try:
            assert written.suffix == ".mcap" and written.exists()
            page.wait_for_timeout(500)
            page.click("#record")
            page.wait_for_function("() => document.getElementById('record-label').textContent.startsWith('Saved')",
                                   timeout=5000)
            assert page.text_content("#record-path") == shown and page.text_content("#record") == "Record"
            assert written.stat().st_size > 0
        finally:
            written.unlink(missing_ok=True)
            page.close()


def test_the_end_of_a_replay_is_shown(browser, tmp_path):
    capture = tmp_path / "press.bin"
    subprocess.run([TACTILE, "sim", "--capture", str(capture), "--seconds", "3", "--scene", "press", "--rate", "250"],
                   check=True, capture_output=True, timeout=20)
    with tactile("replay", str(capture), "--serve", cwd=tmp_path) as url:
        if "state" not in get_json(url + "health")["link"]:
            pytest.skip("backend lacks the /health field link.state (== 'finished' when a replay reaches its end), "
                        "which the dashboard's 'Replay finished' banner is driven by")
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        page.wait_for_selector('#status[data-state="finished"]', timeout=15_000)
        assert get_json(url + "health")["link"]["state"] == "finished"
        assert page.text_content("#status").startswith("Replay finished")
        assert int(page.get_attribute('section[data-sensor="0"]', "data-frames")) > 0  # its last frames stay on screen
        page.screenshot(path=str(REPLAY_SCREENSHOT))
        page.close()


def history_trace(page, sensor):
    """(columns, rows) of a grid's history canvas that its orange ΣF trace crosses (the legend left out)."""
    return page.evaluate(
        """(sensor) => {
            const canvas = document.querySelector(`section[data-sensor="${sensor}"] canvas.history`);
            const { width, height, data } = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height);
            const columns = new Set(), rows = new Set();
            for (let y = 12; y < height; y++) for (let x = 0; x < width; x++) {
                const i = 4 * (y * width + x);
                if (data[i] > 200 && data[i + 1] > 140 && data[i + 1] < 210 && data[i + 2] < 120) { columns.add(x); rows.add(y); }
            }
            return [columns.size, rows.size];
        }""",
        sensor,
    )


def test_a_page_opened_after_a_replay_has_ended_shows_its_last_frames(browser, tmp_path):
    """The stream has nothing more to send once a replay has ended: a page
    opened then still draws each sensor's last frame and the history of the
    replay's end, not "waiting for data…"."""
    capture = tmp_path / "press.bin"
    # 2 s: the quiet second the tare needs, then the press rising to its 5 N peak at the very end.
    subprocess.run([TACTILE, "sim", "--capture", str(capture), "--seconds", "2", "--scene", "press", "--rate", "250"],
                   check=True, capture_output=True, timeout=20)
    with tactile("replay", str(capture), "--serve", "--speed", "2", cwd=tmp_path) as url:
        deadline = time.monotonic() + 15
        while get_json(url + "health")["link"].get("state") != "finished":
            assert time.monotonic() < deadline, "the replay never finished"
            time.sleep(0.1)
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        page.wait_for_selector('#status[data-state="finished"]', timeout=5000)
        sync_api.expect(page.locator(".panel .meta")).to_have_text([re.compile("^seq ")] * 2, timeout=10_000)
        last = get_json(url + "sensors/0/latest")
        assert page.text_content('section[data-sensor="0"] .meta').startswith(f"seq {last['header']['seq']} · ")
        assert taxel_pixel(page, 0, 27, 8)[0] > 200 and taxel_pixel(page, 0, 0, 8)[0] < 20  # the pressed taxel is hot
        columns, rows = history_trace(page, 0)
        assert columns > 20 and rows > 30  # the replay's end is plotted, the press rising
        page.close()


def test_each_panel_says_which_calibration_its_forces_rest_on(browser, tmp_path):
    """An uploaded calibration is stored in the registry the service was given
    and named, with its age, under the grid; the quad says it runs on the
    paper's built-in fits."""
    registry = tmp_path / "registry.sqlite3"
    with tactile("serve", "--source", "sim://?sensors=grid,quad", "--registry", str(registry), cwd=tmp_path) as url:
        body = json.dumps({"sensitivity_pct_per_N": [1.3] * 64}).encode()
        request = urllib.request.Request(url + "sensors/0/calibration", body, method="PUT",
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as response:
            stored = json.load(response)
        assert stored["stored"] and stored["active"]
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        grid = page.locator('.panel[data-sensor="0"] .calibration')
        quad = page.locator('.panel[data-sensor="1"] .calibration')
        page.wait_for_function("document.querySelector('.panel[data-sensor=\"1\"] .calibration')?.textContent.length > 0",
                               timeout=10_000)
        assert grid.text_content().startswith(f"calibration {stored['id']}, 0.0 h old")
        assert "builtin" not in (grid.get_attribute("class") or "").split()
        assert quad.text_content().startswith("calibration: built-in builtin-fits34-35 (the paper's, not measured")
        page.close()
    from service.calibration.registry import Registry

    with Registry(registry) as kept:  # the upload outlives the service
        assert kept.get(stored["id"])["taxels"]["sensitivity_pct_per_N"] == [1.3] * 64


def test_two_boards_with_the_same_sensor_ids_get_a_panel_each_and_a_lost_one_is_named(browser, tmp_path):
    """Both boards have a sensor 0: two panels, each under its board's heading;
    the board whose device is not there is named in the banner."""
    absent = f"socket://127.0.0.1:{free_port()}"  # nothing listens there
    with tactile("serve", "--source", "left=sim://?scene=press&rate=250&sensors=grid,quad",
                 "--source", "right=sim://?scene=press&rate=250&sensors=quad&seed=3", cwd=tmp_path) as url:
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        page.wait_for_function("() => document.querySelectorAll('.panel[data-frames]').length === 3", timeout=10_000)
        groups = page.eval_on_selector_all(
            "section.board", "els => els.map(g => [g.querySelector('.board-title').innerText, "
                             "[...g.querySelectorAll('.panel')].map(p => p.querySelector('h3').innerText)])")
        assert sorted(groups) == [["board left", ["grid0 · grid 8×8", "quad1 · quad"]], ["board right", ["quad0 · quad"]]]
        page.wait_for_selector('#status[data-state="ok"]', timeout=5000)
    with tactile("serve", "--source", "left=sim://?scene=press&rate=250", "--source", f"arm={absent}",
                 cwd=tmp_path) as url:
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(url)
        page.wait_for_selector('#status[data-state="down"]', timeout=10_000)
        assert page.text_content("#status").startswith("board arm: Link down")
        page.wait_for_function("() => document.querySelectorAll('.panel[data-frames]').length === 2", timeout=10_000)


def test_a_gateways_dashboard_shows_every_board_and_names_a_lost_one(browser, tmp_path):
    """Two `tactile serve --zenoh` and a `tactile gateway`: the gateway's
    dashboard has both boards' panels under their headings; one service
    stopped, the banner names its board as down."""
    endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in range(2)]
    zenoh = ("--zenoh", "--no-multicast", "--zenoh-listen")
    with contextlib.ExitStack() as stays, contextlib.ExitStack() as goes:
        stays.enter_context(tactile("serve", "--source", "arm-a=sim://?scene=press&rate=250&sensors=grid,quad",
                                    *zenoh, endpoints[0], cwd=tmp_path))
        goes.enter_context(tactile("serve", "--source", "arm-b=sim://?scene=press&rate=250&sensors=quad",
                                   *zenoh, endpoints[1], cwd=tmp_path))
        gateway = stays.enter_context(tactile("gateway", "--no-multicast", "--zenoh-endpoint", endpoints[0],
                                              "--zenoh-endpoint", endpoints[1], cwd=tmp_path))
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(gateway)
        page.wait_for_function("() => document.querySelectorAll('.panel[data-frames]').length === 3", timeout=15_000)
        titles = sorted(page.eval_on_selector_all(".board-title", "els => els.map(e => e.innerText)"))
        assert titles == ["board arm-a", "board arm-b"]
        page.wait_for_selector('#status[data-state="ok"]', timeout=5000)
        goes.close()  # arm-b's service stops
        page.wait_for_selector('#status[data-state="down"]', timeout=5000)
        assert page.text_content("#status").startswith("board arm-b: Link down")
