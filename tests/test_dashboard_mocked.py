"""The dashboard against a scripted service: Playwright serves web/ and answers
the REST calls and the WebSocket itself, so each test chooses exactly the
frames and health the page sees (a press that jumps between taxels, each link
state, several boards, an old and a new recording endpoint) and checks what
is drawn, from the canvas pixels or the text shown.
"""
import copy
import json
import re
from pathlib import Path

import pytest

from tests.chromium import VIEWPORT, sync_api

WEB = Path(__file__).resolve().parents[1] / "web"
BASE = "http://tactile.test/"
CONTENT_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}
ROWS = COLS = 8
HEALTH = {
    "status": "ok", "replay": False, "recording": None,
    "link": {"source": "sim://", "up": True, "state": "up", "last_error": None, "reconnects": 0, "last_data_age_s": 0.001},
    "stream": {"crc_errors": 0, "bytes_discarded": 0},
    "sensors": {"0": {"kind": "grid", "rate_hz": 1000.0, "seq_gaps": 0}},
    "latency": {"published": {"p99_ms": 1.5}},
}


def grid_frame(seq, forces, stamp=None, sensor=0):
    """A grid frame with the service's contact summary (taxels above 0.05 N; no σ sent)."""
    active = [i for i, f in enumerate(forces) if f > 0.05]
    total = sum(forces[i] for i in active)
    centre = (lambda axis: sum(axis(i) * 4.0 * forces[i] for i in active) / total) if total else (lambda axis: None)
    return {
        "header": {"sensor_id": sensor, "sensor_name": f"grid{sensor}", "kind": "grid", "seq": seq,
                   "board_time_us": seq * 1000, "stamp": seq / 1000 if stamp is None else stamp},
        "rows": ROWS, "cols": COLS, "force_N": forces, "flags": [], "taxel_flags": {},
        "contact": {"total_N": total, "cop_x_mm": centre(lambda i: i % COLS - (COLS - 1) / 2),
                    "cop_y_mm": centre(lambda i: i // COLS - (ROWS - 1) / 2), "area_mm2": 16.0 * len(active),
                    "contacts": 1 if active else 0},
    }


def pressed(loads):
    forces = [0.0] * (ROWS * COLS)
    for index, force in loads.items():
        forces[index] = force
    return forces


class ScriptedService:
    """Answers the dashboard's requests; `record_start` decides POST /record/start."""

    def __init__(self, page):
        self.page = page
        self.health = copy.deepcopy(HEALTH)
        self.sensors = {"board": {"board": "sim"}, "sensors": [{"id": 0, "kind": "grid", "rows": ROWS, "cols": COLS, "name": "grid0"}]}
        self.recording = None
        self.history = []  # of sensor 0
        self.record_start = lambda body: (200, {"path": f"/srv/recordings/{body['name']}", "raw_path": None, "active": True, "messages": 0})
        self.posts = []
        self.tare = lambda query: (200, {"tared": [0], "frames": 100})  # query: the POST /tare's, e.g. "force=true"
        self.socket = None
        page.route(f"{BASE}**", self.answer)
        page.route_web_socket(re.compile(r".*/ws(\?.*)?$"), self.connected)

    def connected(self, socket):
        self.socket = socket

    def json(self, route, body, status=200):
        route.fulfill(status=status, content_type="application/json", body=json.dumps(body))

    def answer(self, route):
        path = route.request.url[len(BASE) - 1:].split("?")[0]
        if path == "/" or path.startswith("/static/"):
            file = WEB / ("index.html" if path == "/" else path[len("/static/"):])
            return route.fulfill(path=str(file), content_type=CONTENT_TYPES[file.suffix])
        if route.request.method == "POST":
            return self.answer_post(route, path)
        answers = {"/health": lambda: {**self.health, "recording": self.recording}, "/sensors": lambda: self.sensors,
                   "/record": lambda: self.recording, "/sensors/0/history": lambda: self.history}
        self.json(route, answers[path]())

    def answer_post(self, route, path):
        body = route.request.post_data_json
        self.posts.append((path, body))
        if path == "/record/start":
            status, answer = self.record_start(body)
            self.recording = answer if status == 200 else self.recording
            return self.json(route, answer, status)
        if path == "/record/stop":
            self.recording = {**self.recording, "active": False, "messages": 1234}
            return self.json(route, self.recording)
        if path == "/tare":
            status, answer = self.tare(route.request.url.partition("?")[2])
            return self.json(route, answer, status)
        self.json(route, {})

    def open(self):
        self.page.goto(BASE)
        self.page.wait_for_function("() => document.querySelector('section.panel')")
        assert self.socket is not None

    def send(self, frames, sensor=0):
        """Sends frames (of ``sensor``) and returns once the page has drawn them."""
        before = int(self.page.get_attribute(f'section[data-sensor="{sensor}"]', "data-frames") or 0)
        self.socket.send(json.dumps({"type": "frames", "frames": frames}))
        self.page.wait_for_selector(f'section[data-sensor="{sensor}"][data-frames="{before + len(frames)}"]')
        self.page.evaluate("() => new Promise(done => requestAnimationFrame(() => requestAnimationFrame(done)))")

    def poll(self):
        self.page.evaluate("() => pollHealth()")


@pytest.fixture
def service(browser):
    page = browser.new_page(viewport=VIEWPORT)
    yield ScriptedService(page)
    page.close()


def pixels_around(page, index, reach=0.7, reach_y=None):
    """Canvas pixels of the box reaching `reach` cells (`reach_y` up and down) from a taxel's centre, as [r, g, b, a, ...]."""
    return page.evaluate(
        """([index, cols, reach, reachY]) => {
            const canvas = document.querySelector('section[data-sensor="0"] canvas.live');
            const cell = canvas.width / cols, r = Math.floor(index / cols), c = index % cols;
            const x = Math.round((c + 0.5 - reach) * cell), y = Math.round((r + 0.5 - reachY) * cell);
            return Array.from(canvas.getContext("2d").getImageData(x, y, Math.round(2 * reach * cell),
                                                                   Math.round(2 * reachY * cell)).data);
        }""",
        [index, COLS, reach, reach if reach_y is None else reach_y],
    )


def cyan_pixels(rgba):
    return sum(1 for i in range(0, len(rgba), 4) if rgba[i] < 100 and rgba[i + 1] > 180 and rgba[i + 2] > 180)


def differing_pixels(a, b):
    return sum(1 for i in range(0, len(a), 4) if max(abs(a[i + k] - b[i + k]) for k in range(3)) > 48)


def test_a_moved_press_leaves_no_outline_or_cross_behind(service):
    service.open()
    first, second, reference = 27, 45, 9  # (row 4, col 4) → (row 6, col 6); row 2, col 2 is never pressed
    service.send([grid_frame(1, pressed({first: 3.0, reference: 0.03}))])
    loaded = pixels_around(service.page, first)
    assert cyan_pixels(loaded) > 50  # the outline is seen where it is drawn …
    assert differing_pixels(loaded, pixels_around(service.page, reference)) > 500  # … and so are the heat and the ring
    service.send([grid_frame(2, pressed({second: 3.0, first: 0.03, reference: 0.03}))])
    left = pixels_around(service.page, first)
    assert cyan_pixels(left) == 0
    # Where the press was, the canvas now looks exactly like a taxel that was never pressed.
    assert differing_pixels(left, pixels_around(service.page, reference)) < len(left) // 400
    assert cyan_pixels(pixels_around(service.page, second)) > 50


def test_a_taxel_within_its_noise_is_not_outlined_as_in_contact(service):
    """The service's contact rule (above 0.05 N and 4 σ): a 0.2 N taxel whose
    σ is 0.06 N (a low-C0 sensor's noise) is no contact and the page drew it
    as one (its own fixed 0.05 N); 0.3 N at that σ is."""
    service.open()
    frame = grid_frame(1, pressed({27: 0.2, 45: 0.3}))
    frame["sigma_N"] = [0.06] * (ROWS * COLS)
    service.send([frame])
    assert cyan_pixels(pixels_around(service.page, 27)) == 0
    assert cyan_pixels(pixels_around(service.page, 45)) > 50


def test_the_centre_of_pressure_ring_leaves_the_number_uncovered(service):
    service.open()
    frame = grid_frame(1, pressed({27: 2.24}))
    service.send([frame])
    number = {"reach": 0.3, "reach_y": 0.15}  # the box of the taxel's number, inside the ring
    with_ring = pixels_around(service.page, 27, **number)
    frame = copy.deepcopy(frame)
    frame["header"]["seq"] = 2
    frame["contact"].update(cop_x_mm=None, cop_y_mm=None)
    service.send([frame])
    assert differing_pixels(with_ring, pixels_around(service.page, 27, **number)) == 0


def test_history_of_a_steady_load_sits_below_a_labelled_top(service):
    service.open()
    service.send([grid_frame(seq, pressed({27: 4.0}), stamp=100 + seq / 20) for seq in range(200)])  # 10 s of 4 N
    top = float(service.page.get_attribute('section[data-sensor="0"] canvas.history', "data-top"))
    assert top >= 4.0 * 1.2
    # The orange trace's highest pixel (legend swatch excluded) sits well below the plot's top edge.
    rows_with_trace = service.page.evaluate(
        """() => {
            const canvas = document.querySelector('section[data-sensor="0"] canvas.history');
            const { width, height, data } = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height);
            const rows = [];
            for (let y = 12; y < height; y++) for (let x = 60; x < width; x++) {
                const i = 4 * (y * width + x);
                if (data[i] > 200 && data[i + 1] > 140 && data[i + 1] < 210 && data[i + 2] < 120) { rows.push(y); break; }
            }
            return { rows, height };
        }"""
    )
    plot_top, plot_height = 16, rows_with_trace["height"] - 34
    assert rows_with_trace["rows"], "no trace drawn"
    assert min(rows_with_trace["rows"]) > plot_top + 0.1 * plot_height


def test_a_sensor_silent_when_the_page_opens_is_drawn_from_its_last_seconds(service):
    """The stream sends nothing for it (a replay that has ended, a board gone
    quiet): its last frame and history come from /sensors/0/history."""
    service.health["sensors"]["0"]["stale"] = True
    service.history = [grid_frame(seq, pressed({27: seq / 25}), stamp=100 + seq / 30) for seq in range(1, 101)]
    service.open()
    service.page.wait_for_selector('section[data-sensor="0"][data-frames="100"]', timeout=5000)
    service.page.evaluate("() => new Promise(done => requestAnimationFrame(() => requestAnimationFrame(done)))")
    assert service.page.text_content('section[data-sensor="0"] .meta').startswith("seq 100 · ΣF 4.00 N")
    cell = pixels_around(service.page, 27, reach=0.45)
    orange = sum(1 for i in range(0, len(cell), 4) if cell[i] > 250 and 120 < cell[i + 1] < 190)  # 4 N's colour
    assert orange > len(cell) // 4 // 4  # a quarter of the cell: the rest is its number and the centre of pressure
    assert float(service.page.get_attribute('section[data-sensor="0"] canvas.history', "data-top")) >= 4.0


@pytest.mark.parametrize("link, replay, state, words", [
    ({"state": "up"}, False, "ok", ["Live", "sim://"]),
    ({"state": "stale", "last_data_age_s": 3.24}, False, "stale", ["no data for 3.2 s"]),
    ({"state": "down", "up": False, "last_error": "device reports readiness to read but returned no data"}, False, "down",
     ["Link down", "returned no data"]),
    ({"state": "up", "source": "replay:///tmp/x.mcap"}, True, "replay", ["Replay", "/tmp/x.mcap"]),
    ({"state": "finished", "source": "replay:///tmp/x.mcap"}, True, "finished", ["Replay finished"]),
    ({"state": None, "up": False, "last_error": "[Errno 2] no such device"}, False, "down", ["no such device"]),
    ({"state": None, "last_data_age_s": 5.0}, False, "stale", ["no data for 5.0 s"]),
], ids=["up", "stale", "down", "replay", "finished", "down-without-state", "stale-without-state"])
def test_status_banner_names_each_link_state(service, link, replay, state, words):
    service.health["link"].update(link)
    if link["state"] is None:
        del service.health["link"]["state"]  # a service that predates link.state
    service.health["replay"] = replay
    service.open()
    service.poll()
    assert service.page.get_attribute("#status", "data-state") == state
    text = service.page.text_content("#status")
    assert all(word in text for word in words), text


def test_a_degraded_service_says_why_in_the_banner(service):
    service.health["status"] = "degraded"
    service.health["problems"] = ["sensor 0: channels [5] have no zero (no plausible reading while it tared): "
                                  "their forces are null", "sensor 3 stale"]
    service.open()
    service.poll()
    assert service.page.get_attribute("#status", "data-state") == "degraded"
    text = service.page.text_content("#status")
    # The most severe first: a silent sensor before null channels (all are listed: the next test).
    assert "service degraded · sensor 3 stale (+1 more)" in text


def test_a_sensor_whose_frames_are_dropped_ranks_with_the_silent_ones(service):
    """Its frames come and none is read: no data, as a stale sensor has none, above null channels and above
    the board's ERROR frames and corrupt frames (its data partly lost, partly read)."""
    dropped = ("sensor 2: 900 frames dropped in the last 10 s: 256-byte GRID frames where the board's INFO "
               "describes a 4x6 grid (96 bytes)")
    null = "sensor 0: channels [5] have no zero (no plausible reading while it tared): their forces are null"
    errors = "the board sent 30 ERROR frames in the last 10 s, the latest: \"mux settle timeout\""
    corrupt = ("168 of 880 frames (19 %) in the last 10 s failed their CRC check and were dropped, by their headers "
               "from sensor 1 (168): a loose cable or connector, electrical noise, or a wrong baud rate?")
    service.health.update(status="degraded", problems=[errors, corrupt, null, dropped])
    service.open()
    service.poll()
    assert f"service degraded · {dropped} (+3 more)" in service.page.text_content("#status")
    assert service.page.locator("#problems li").all_inner_texts() == [dropped, null, errors, corrupt]


def test_stats_have_no_stray_separators_without_a_board(service):
    service.health.update(sensors={}, stream={}, latency={"published": {"p99_ms": None}})
    service.open()
    service.poll()
    stats = service.page.text_content("#stats")
    assert "CRC" not in stats and not stats.startswith(" ·") and "· ·" not in stats


def test_panels_are_grouped_by_board_when_there_are_several(service):
    service.sensors["sensors"] = [
        {"id": 3, "kind": "quad", "rows": 2, "cols": 2, "name": "quad3", "board": "left"},
        {"id": 0, "kind": "grid", "rows": ROWS, "cols": COLS, "name": "grid0", "board": "right"},
        {"id": 1, "kind": "grid", "rows": ROWS, "cols": COLS, "name": "grid1", "board": "left"},
        {"id": 2, "kind": "quad", "rows": 2, "cols": 2, "name": "quad2", "board": "right"},
    ]
    service.open()
    service.page.wait_for_function("() => document.querySelectorAll('section.panel').length === 4")
    groups = service.page.eval_on_selector_all(
        "section.board", "els => els.map(g => [g.querySelector('.board-title').innerText, "
                         "[...g.querySelectorAll('section.panel')].map(p => Number(p.dataset.sensor))])")
    assert groups == [["board right", [0, 2]], ["board left", [1, 3]]]


def test_one_board_has_no_board_heading(service):
    service.open()
    assert service.page.locator(".board-title").is_hidden()


def old_record_start(body):
    if "path" not in body:
        return 422, {"detail": [{"type": "missing", "loc": ["body", "path"], "msg": "Field required"}]}
    return 200, {"path": body["path"], "raw_path": None, "active": True, "messages": 0}


@pytest.mark.parametrize("backend", ["name", "path"])
def test_record_button_shows_where_the_file_goes_with_either_backend(service, backend):
    if backend == "path":
        service.record_start = old_record_start
    service.open()
    service.page.click("#record")
    service.page.wait_for_selector("#record-info:not([hidden])")
    started = service.recording["path"]
    assert service.page.text_content("#record-path") == started
    assert "Recording" in service.page.text_content("#record-label")
    assert service.page.text_content("#record") == "Stop recording"
    bodies = [body for path, body in service.posts if path == "/record/start"]
    name = bodies[0]["name"]
    assert re.fullmatch(r"recording-[0-9T-]+Z\.mcap", name)
    assert bodies[1:] == ([] if backend == "name" else [{"path": name}])
    service.page.click("#record")
    service.page.wait_for_function("() => document.getElementById('record-label').textContent.startsWith('Saved')")
    assert service.page.text_content("#record-path") == started
    assert service.page.text_content("#record") == "Record"
    service.page.click("#record")  # again: an old service is asked by path straight away
    service.page.wait_for_selector("text=Stop recording")
    again = [body for path, body in service.posts if path == "/record/start"][len(bodies):]
    assert [list(body) for body in again] == [[backend]]


def quad_frame(seq, force, stamp, sensor=0, flags=()):
    """A quad frame: force (x, y, z) in N, None for a component the service could not give; σ 0.5 N each."""
    x, y, z = force
    return {"header": {"sensor_id": sensor, "sensor_name": f"quad{sensor}", "kind": "quad", "seq": seq,
                       "board_time_us": seq * 1000, "stamp": stamp},
            "wrench": {"force": {"x": x, "y": y, "z": z}},
            "wrench_sigma": {"force": {k: None if v is None else 0.5 for k, v in zip("xyz", force)}},
            "contact": None, "flags": list(flags), "taxel_flags": {}}


# By hue, so a line's anti-aliased edge on the dark plot counts too; the axes and labels are grey.
TRACE_COLOURS = {"orange": "d[i] - d[i + 2] > 60 && d[i] > d[i + 1]",    # ΣF, Fz (#ffb74d)
                 "blue": "d[i + 2] - d[i] > 60 && d[i + 1] > d[i]"}      # |Fxy| (#4fc3f7)


def trace_span(page, colour, sensor=0):
    """(first, last) x of a history trace's pixels, as fractions of the plot's width (0 = −10 s, 1 = its
    newest sample); None without any. The legend's swatches (above y = 12) are left out."""
    return page.evaluate(
        """([sensor, test]) => {
            const canvas = document.querySelector(`section[data-sensor="${sensor}"] canvas.history`);
            const scale = canvas.width / canvas.clientWidth, d = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
            const plotX = 34 * scale, plotW = canvas.width - 42 * scale, hit = new Function("d", "i", `return ${test}`);
            const xs = [];
            for (let x = Math.ceil(plotX); x < canvas.width; x++)
                for (let y = Math.ceil(12 * scale); y < canvas.height; y++) if (hit(d, 4 * (y * canvas.width + x))) { xs.push(x); break; }
            return xs.length ? [(xs[0] - plotX) / plotW, (xs[xs.length - 1] - plotX) / plotW] : null;
        }""",
        [sensor, TRACE_COLOURS[colour]],
    )


def test_a_grid_taring_shows_no_total_and_its_history_a_gap(service):
    """While a sensor tares the service gives no contact (null) and flags taring: the page said
    "ΣF 0.00 N · contacts 0 · area 0 mm²" and drew ΣF = 0 N for those seconds."""
    service.open()
    loaded = [grid_frame(seq, pressed({27: 4.0}), stamp=100 + seq / 20) for seq in range(100)]  # 5 s of 4 N
    taring = []
    for seq in range(100, 200):  # then 5 s taring: forces and contact null
        frame = grid_frame(seq, [0.0] * (ROWS * COLS), stamp=100 + seq / 20)
        frame.update(force_N=[None] * (ROWS * COLS), contact=None, flags=["taring"])
        taring.append(frame)
    service.send(loaded + taring)
    span = trace_span(service.page, "orange")
    assert span[0] < 0.05 and 0.45 < span[1] < 0.55, span  # the trace ends where the taring began, half way
    meta = service.page.text_content('section[data-sensor="0"] .meta')
    assert "ΣF —" in meta and "contacts —" in meta and "area —" in meta, meta
    assert "0.00" not in meta and "contacts 0" not in meta


def test_a_quad_with_an_open_electrode_leaves_a_gap_in_its_history(service):
    """An open electrode: wrench x, y, z null. The text said "—" while Fz and |Fxy| drew a flat 0 N line."""
    service.sensors["sensors"] = [{"id": 0, "kind": "quad", "rows": 2, "cols": 2, "name": "quad0"}]
    service.open()
    good = [quad_frame(seq, (3.0, 4.0, 8.0), stamp=100 + seq / 20) for seq in range(100)]
    opened = [quad_frame(seq, (None, None, None), stamp=100 + seq / 20, flags=["open_channel"]) for seq in range(100, 200)]
    service.send(good + opened)
    assert "Fz — N" in service.page.text_content('section[data-sensor="0"] .meta')
    for colour in ("orange", "blue"):  # Fz 8 N, |Fxy| 5 N
        span = trace_span(service.page, colour)
        assert span[0] < 0.05 and 0.45 < span[1] < 0.55, (colour, span)


@pytest.mark.parametrize("age, state", [(3.0, "stale"), (0.3, "ok")])
def test_a_link_reported_up_is_not_live_once_its_data_is_older_than_the_stale_threshold(service, age, state):
    """/health's stale threshold is link.stale_after_s (here 0.5 s): data 3 s old is stale whatever link.state says."""
    service.health["link"].update(state="up", last_data_age_s=age, stale_after_s=0.5)
    service.open()
    service.poll()
    assert service.page.get_attribute("#status", "data-state") == state
    text = service.page.text_content("#status")
    assert ("Live" in text) == (state == "ok"), text
    if state == "stale":
        assert "no data for 3.0 s" in text


def test_a_silent_sensor_is_marked_stale_with_its_age_and_greyed(service):
    """A quad under 8 N goes silent: /health says stale, last frame 10.8 s old. The panel went on showing
    "Fz 8.01 ± 0.56 N" and its shear as current, its history ending at "now"."""
    service.sensors["sensors"] = [{"id": 0, "kind": "quad", "rows": 2, "cols": 2, "name": "quad0"}]
    service.health["sensors"] = {"0": {"id": 0, "kind": "quad", "rate_hz": 1000.0, "stale": False,
                                       "last_frame_age_s": 0.002}}
    service.open()
    service.send([quad_frame(seq, (6.0, 0.0, 8.0), stamp=100 + seq / 20) for seq in range(40)])
    service.poll()
    panel = 'section[data-sensor="0"]'
    live_opacity = f"() => Number(getComputedStyle(document.querySelector('{panel} canvas.live')).opacity)"
    assert "stale" not in service.page.inner_text(panel) and service.page.evaluate(live_opacity) == 1
    service.health["sensors"]["0"].update(rate_hz=0.0, stale=True, last_frame_age_s=10.8)
    service.poll()
    service.page.evaluate("() => new Promise(done => requestAnimationFrame(() => requestAnimationFrame(done)))")
    assert "stale · last frame 10.8 s ago" in service.page.inner_text(panel)
    assert service.page.evaluate(live_opacity) < 0.5  # the last wrench is greyed, not shown as current
    assert service.page.get_attribute(f"{panel} canvas.history", "data-end") == "last frame"
    service.health["sensors"]["0"].update(rate_hz=1000.0, stale=False, last_frame_age_s=0.002)  # it speaks again
    service.poll()
    assert "stale" not in service.page.inner_text(panel) and service.page.evaluate(live_opacity) == 1


def test_every_problem_is_listed_the_most_severe_first(service):
    """Two boards: the banner showed problems[0] "(+2 more)", hiding board b's stale sensor."""
    minor = "board a: sensor 0 uses the built-in calibration: its own could not be used (no such file)"
    null = "board a: sensor 0: channels [5] have no zero (no plausible reading while it tared): their forces are null"
    stale = "board b: sensor 1 stale"
    service.health.update(status="degraded", problems=[minor, null, stale])
    service.open()
    service.poll()
    assert "service degraded · board b: sensor 1 stale (+2 more)" in service.page.text_content("#status")
    items = service.page.locator("#problems li")
    assert items.all_inner_texts() == [stale, null, minor]
    assert all(items.nth(k).is_visible() for k in range(3))
    service.health.update(status="ok", problems=[])
    service.poll()
    assert service.page.locator("#problems").is_hidden()


def tare_said(service):
    """Clicks "Tare all" and returns what the page then says of it ("" when nothing within 2 s)."""
    said = "() => { const info = document.getElementById('tare-info'); return info && !info.hidden ? info.innerText : ''; }"
    service.page.click("#tare")
    try:
        service.page.wait_for_function(f"() => ({said})() !== ''", timeout=2000)
    except sync_api.TimeoutError:
        return ""
    return service.page.evaluate(said)


def test_a_refused_tare_says_why(service):
    """The service on --token, the page without ?token=: 401, and the page said nothing."""
    detail = "this endpoint needs 'Authorization: Bearer <token>' (printed by tactile serve)"
    service.tare = lambda query: (401, {"detail": detail})
    service.open()
    assert tare_said(service) == f"Tare failed (401): {detail}"


@pytest.mark.parametrize("confirm", [True, False])
def test_a_tare_of_loaded_taxels_says_what_became_of_it(service, confirm):
    """409 (taxels loaded), the user asked: the ?force=true retry's answer was never looked at."""
    loaded = {"detail": {"error": "taxels read loaded", "loaded_taxels": {"0": [27, 28]}}}
    service.tare = lambda query: (500, {"detail": "the board is gone"}) if query == "force=true" else (409, loaded)
    dialogs = []
    service.page.on("dialog", lambda d: (dialogs.append(d.message), d.accept() if confirm else d.dismiss()))
    service.open()
    said = tare_said(service)
    assert "sensor 0: taxels 27, 28" in dialogs[0]
    if confirm:
        assert said == "Tare failed (500): the board is gone"
        assert [path for path, _ in service.posts] == ["/tare", "/tare"]
    else:
        assert said == "Not tared: sensor 0: taxels 27, 28 read loaded"


def test_a_tare_says_which_sensors_it_tared_and_which_not(service):
    """Board b down: the answer lists only a's sensors, and the page said nothing at all."""
    service.sensors["sensors"] = [{"id": i, "kind": "grid", "rows": ROWS, "cols": COLS, "name": f"grid{i}", "board": board}
                                  for board, ids in (("a", (0, 1)), ("b", (2, 3))) for i in ids]
    note = "board b not connected: the tare takes its next frames once it is back"
    service.tare = lambda query: (200, {"tared": ["a/0", "a/1"], "frames": 100, "note": note})
    service.open()
    service.page.wait_for_function("() => document.querySelectorAll('section.panel').length === 4")
    assert tare_said(service) == f"Tared sensors a/0, a/1 · not tared: b/2, b/3 · {note}"


def test_a_tare_on_one_board_names_the_sensors_tared(service):
    """One board: the service answers with bare ids."""
    service.sensors["sensors"].append({"id": 1, "kind": "quad", "rows": 2, "cols": 2, "name": "quad1"})
    service.tare = lambda query: (200, {"tared": [0, 1], "frames": 100})
    service.open()
    service.page.wait_for_function("() => document.querySelectorAll('section.panel').length === 2")
    assert tare_said(service) == "Tared sensors 0, 1"


def hover_taxel(page, index, sensor=0):
    """Moves the mouse to the centre of a taxel's cell on the page."""
    box = page.locator(f'section[data-sensor="{sensor}"] canvas.live').bounding_box()
    cell = box["width"] / COLS
    page.mouse.move(box["x"] + (index % COLS + 0.5) * cell, box["y"] + (index // COLS + 0.5) * cell)


def test_a_grid_shows_each_taxels_sigma(service):
    """The API gives each taxel's σ (1.69 ± 0.12 N); the grid showed "1.69" alone, no σ anywhere."""
    service.open()
    forces = pressed({27: 1.69, 45: 0.8, 5: 0.0})
    frame = grid_frame(1, forces)
    frame.update(sigma_N=[0.12 if i == 27 else 0.05 if i == 45 else 0.01 for i in range(ROWS * COLS)],
                 taxel_flags={"crosstalk_corrected": [27, 45], "out_of_range": [5]})
    frame["force_N"][5] = frame["sigma_N"][5] = None
    service.send([frame])
    panel = 'section[data-sensor="0"]'
    assert "max 1.69 ± 0.12 N (taxel 27)" in service.page.text_content(f"{panel} .meta")
    readout = f"{panel} .taxel-readout"
    hover_taxel(service.page, 27)
    assert service.page.inner_text(readout) == "taxel 27 (row 3, col 3): 1.69 ± 0.12 N · crosstalk corrected"
    frame = copy.deepcopy(frame)
    frame["header"]["seq"] = 2
    frame["force_N"][27], frame["sigma_N"][27] = 2.0, 0.15
    service.send([frame])  # the readout follows the frames while the mouse rests
    assert service.page.inner_text(readout) == "taxel 27 (row 3, col 3): 2.00 ± 0.15 N · crosstalk corrected"
    hover_taxel(service.page, 5)
    assert service.page.inner_text(readout) == "taxel 5 (row 0, col 5): — · out of range"
    service.page.mouse.move(0, 0)
    assert "taxel" not in service.page.inner_text(readout).replace("a taxel", "")
