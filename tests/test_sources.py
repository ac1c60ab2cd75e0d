"""Source URLs: what is refused at start-up, what is waited for."""
import re
import time

import pytest

from service import cli
from service.sources import check_source


@pytest.mark.parametrize("url, named", [
    ("sim://?scene=bogus", "unknown scene 'bogus'"),
    ("sim://?colour=red", "unknown option 'colour'"),
    ("replay://no-such-run.mcap", "no such recording: no-such-run.mcap"),
    ("bogus://x", "no handler for bogus://"),
    ("a.b://x", "'a.b' is no URL scheme"),
])
def test_a_source_that_can_never_open_is_refused_before_the_service_starts(url, named):
    with pytest.raises(ValueError, match=re.escape(named)):
        check_source(url)


@pytest.mark.parametrize("url, opens_now", [("/dev/ttyACM_not_plugged_in", False), ("socket://127.0.0.1:9", False),
                                            ("sim://?scene=press&rate=500", True)])
def test_a_source_that_may_appear_later_or_opens_now_passes(url, opens_now):
    from service.sources import open_source

    assert check_source(url) is None  # not refused at start ...
    if opens_now:
        with open_source(url) as source:  # ... and it delivers
            deadline = time.monotonic() + 2
            data = b""
            while len(data) < 1000 and time.monotonic() < deadline:
                data += source.read(0.05)
        assert len(data) >= 1000
    else:
        with pytest.raises(OSError, match=re.escape(url.split("://")[-1])):  # ... but waited for: not there yet
            open_source(url)


def test_tactile_serve_exits_naming_a_bad_source(capsys):
    assert cli.main(["serve", "--source", "sim://?scene=bogus"]) == 2
    assert "unknown scene 'bogus'" in capsys.readouterr().err


def test_a_file_that_is_no_recording_is_refused_as_a_replay_source(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(bytes(range(64)))
    with pytest.raises(ValueError, match="not an MCAP recording"):
        check_source(f"replay://{junk}")


def test_tactile_replay_serve_serves_the_recording_through_the_live_service(tmp_path, monkeypatch):
    import uvicorn
    from fastapi.testclient import TestClient

    from firmware_sim.board import BoardConfig, capture

    run = tmp_path / "run.bin"
    run.write_bytes(capture(BoardConfig(scene="press"), 0.5)[0])
    served = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **options: served.update(app=app, **options))
    assert cli.main(["replay", str(run), "--serve", "--port", "8123", "--speed", "max"]) == 0
    assert served["port"] == 8123
    with TestClient(served["app"], base_url="http://localhost") as client:
        health = client.get("/health").json()
    assert health["replay"] is True and health["link"]["source"].startswith("replay://")
