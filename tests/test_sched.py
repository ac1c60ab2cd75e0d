"""The scheduler latency hint: asked through the real system call, read back
from the kernel, inherited by threads started afterwards."""
import platform
import threading

import pytest
from fastapi.testclient import TestClient

from service import sched
from service.api.app import create_app
from service.live_service import TactileService


def kernel_version() -> tuple[int, int]:
    major, minor = platform.release().split(".")[:2]
    return int(major), int("".join(c for c in minor if c.isdigit()) or 0)


custom_slices = pytest.mark.skipif(
    platform.system() != "Linux" or platform.machine() not in ("x86_64", "aarch64") or kernel_version() < (6, 12),
    reason="a custom fair-scheduler slice needs Linux >= 6.12 on x86_64 or aarch64",
)


def in_new_thread(function):
    """Run ``function`` in a fresh thread (the hint must not stick to pytest's
    own thread) and return what it returned."""
    result = []
    thread = threading.Thread(target=lambda: result.append(function()))
    thread.start()
    thread.join(10)
    return result[0]


@pytest.mark.parametrize("slice_us", [0, 99, 100_001])
def test_a_slice_outside_the_kernels_range_is_refused_naming_it(slice_us):
    with pytest.raises(ValueError, match=f"slice_us={slice_us} is outside 100..100000"):
        sched.request_slice(slice_us)


@custom_slices
def test_the_kernel_grants_the_slice_and_later_threads_inherit_it():
    def ask_then_start_a_thread():
        before = sched.current_slice_us()
        request = sched.request_slice(250)
        return before, request, in_new_thread(sched.current_slice_us)

    before, request, inherited = in_new_thread(ask_then_start_a_thread)
    assert before != 250
    assert request.applied and request.granted_us == 250 and request.error is None
    assert inherited == 250
    assert sched.current_slice_us() == before  # the caller's thread is untouched


def test_without_the_system_call_the_request_reports_why_and_changes_nothing(monkeypatch):
    monkeypatch.setattr(sched.platform, "machine", lambda: "sparc64")
    request = sched.request_slice(100)
    assert not request.applied and request.granted_us is None
    assert request.error == f"sched_setattr is not available on {platform.system()} sparc64"


@custom_slices
def test_health_reports_the_slice_the_service_runs_with():
    service = TactileService("sim://?scene=idle&sensors=quad", sched_slice_us=300)
    with TestClient(create_app(service), base_url="http://localhost") as client:
        scheduling = client.get("/health").json()["scheduling"]
    assert scheduling == {"requested_us": 300, "granted_us": 300, "applied": True, "error": None}


def test_health_reports_the_kernels_slice_when_none_is_asked_for():
    service = TactileService("sim://?scene=idle&sensors=quad")
    with TestClient(create_app(service), base_url="http://localhost") as client:
        scheduling = client.get("/health").json()["scheduling"]
    assert scheduling["requested_us"] is None and scheduling["applied"] is False
    assert scheduling["granted_us"] == sched.current_slice_us()


@pytest.mark.parametrize("text, message", [("50", "slice 50 us is outside 100..100000"),
                                           ("fast", "slice 'fast' must be a whole number")])
def test_serve_refuses_a_bad_slice_naming_it(capsys, text, message):
    from service.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "--sched-slice-us", text])
    assert message in capsys.readouterr().err


def test_serve_takes_a_slice_in_range_or_zero():
    from service.cli import build_parser

    assert build_parser().parse_args(["serve", "--sched-slice-us", "100"]).sched_slice_us == 100
    assert build_parser().parse_args(["serve"]).sched_slice_us == 0
