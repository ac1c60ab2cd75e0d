"""Values a new user mistypes: each refused at once, naming it, never a traceback or a retry for ever."""
import time

import pytest
from fastapi.testclient import TestClient

from service import cli
from service.api.app import create_app
from service.calibration.book import CalibrationBook
from service.calibration.registry import Registry
from service.client import TactileClient, TactileError
from service.live_service import TactileService
from service.sources import check_source


@pytest.mark.parametrize("command", [["calibrations", "list"], ["calibrations", "show", "ab12"]])
def test_a_registry_file_that_is_no_registry_is_named_not_a_traceback(command, tmp_path, capsys):
    """A file that is not SQLite ended in sqlite3.DatabaseError's traceback."""
    bad = tmp_path / "notdb.sqlite3"
    bad.write_bytes(b"not a db")
    assert cli.main(command + ["--registry", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"calibration registry {bad} cannot be used (file is not a database)" in err and "Traceback" not in err


def test_calibrate_says_the_registry_is_unusable_before_its_fit(tmp_path, capsys):
    """`tactile calibrate` fitted for seconds, then died on the registry, its result lost: the
    registry is now opened first (the session named here is not even read)."""
    bad = tmp_path / "notdb.sqlite3"
    bad.write_bytes(b"not a db")
    code = cli.main(["calibrate", str(tmp_path / "absent-session.bin"), "--reference", str(tmp_path / "absent.csv"),
                     "--registry", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and f"calibration registry {bad} cannot be used" in err and "absent-session" not in err


def test_an_upload_to_a_service_whose_registry_is_unusable_is_503_naming_it(tmp_path):
    registry = tmp_path / "r.sqlite3"
    Registry(registry).close()
    service = TactileService("sim://?sensors=quad&rate=200", calibrations=CalibrationBook(registry))
    with TestClient(create_app(service), base_url="http://localhost") as client:
        deadline = time.monotonic() + 10
        while not service.pipeline.latest and time.monotonic() < deadline:
            time.sleep(0.05)
        registry.unlink()
        registry.mkdir()  # the store's file gone, a directory in its place
        answer = client.put("/sensors/0/calibration", json={"normal_fit": [-0.0005, 0.0343], "shear_fit": [0.0077, 0.0]})
    assert answer.status_code == 503 and f"calibration registry {registry} cannot be used" in answer.json()["detail"]


@pytest.mark.parametrize("url, message", [
    ("socket://127.0.0.1", "no port (socket://HOST:PORT)"),
    ("socket://127.0.0.1:abc", "port 'abc' is not 1-65535"),
    ("socket://127.0.0.1:99999", "port '99999' is not 1-65535"),
    ("socket://:9000", "no host"),
    ("rfc2217://lab:0", "port '0' is not 1-65535"),
    ("sim:/?scene=press", "a sim URL begins sim:// (two slashes)"),
])
def test_a_source_url_that_can_never_open_is_named(url, message):
    """serve retried `socket://127.0.0.1` for ever, its reason "'<=' not supported between int and NoneType"."""
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        check_source(url)


@pytest.mark.parametrize("url", ["socket://127.0.0.1:9000", "socket://[::1]:9000", "/dev/ttyACM0", "sim://"])
def test_a_source_url_that_may_open_passes(url):
    check_source(url)


@pytest.mark.parametrize("base_url, message", [
    ("http//localhost:9427", "expected http://HOST[:PORT]"), ("not a url", "no spaces"),
    ("http://[::1:9427", "Invalid IPv6 URL"), ("http://127.0.0.1:9427 ", "no spaces"),
    ("http://127.0.0.1:99999", "Port out of range"),
])
def test_the_client_refuses_a_base_url_no_request_could_use_with_its_own_error(base_url, message):
    """README: every failure raises TactileError; these raised urllib's ValueError from the first request."""
    with pytest.raises(TactileError, match=message.replace("[", r"\[")):
        TactileClient(base_url)


@pytest.mark.parametrize("option, value, message", [
    ("--allow-origin", "lab-pc:3000", "expected http(s)://HOST[:PORT]"),
    ("--allow-origin", "http://lab-pc:3000/page", "expected http(s)://HOST[:PORT]"),
    ("--allow-host", "http://lab-pc", "expected a bare name or address"),
    ("--recordings-dir", None, "is a file, not a directory"),
])
def test_serve_refuses_an_allowance_that_could_never_match_and_a_file_for_a_directory(option, value, message, tmp_path,
                                                                                      capsys):
    """--allow-origin lab-pc:3000 started silently, then its page got 403 'allow it with --allow-origin'."""
    if value is None:
        value = str(tmp_path / "afile")
        (tmp_path / "afile").write_text("")
    with pytest.raises(SystemExit) as exit_:
        cli.main(["serve", "--port", "9", option, value])
    assert exit_.value.code == 2 and message in capsys.readouterr().err
