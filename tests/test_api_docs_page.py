"""/docs and /redoc work on a network without internet: the browser is
refused every request that leaves the service, and the pages still show the
API's endpoints."""
from urllib.parse import urlparse

import pytest

from tests.chromium import VIEWPORT


@pytest.fixture()
def offline_page(served, browser):
    """A page whose requests to any host but the service's are refused, with
    the (resource type, URL) of each refused one."""
    page = browser.new_page(viewport=VIEWPORT)
    own = urlparse(served[0]).netloc
    refused = []

    def route(r):
        if urlparse(r.request.url).netloc == own:
            r.continue_()
        else:
            refused.append((r.request.resource_type, r.request.url))
            r.abort()

    page.route("**/*", route)
    yield page, refused
    page.close()


def test_swagger_page_lists_the_endpoints_offline(served, offline_page):
    page, refused = offline_page
    page.goto(served[0] + "docs")
    page.get_by_text("/sensors/{sensor_id}/tare", exact=True).wait_for(timeout=10_000)
    assert page.locator(".opblock").count() >= 17  # one block an operation
    assert refused == []


def test_redoc_page_lists_the_endpoints_offline(served, offline_page):
    page, refused = offline_page
    page.goto(served[0] + "redoc")
    page.wait_for_selector("text=Calibrated forces from capacitive tactile sensors", timeout=10_000)
    assert page.locator("h1", has_text="tactile").count() == 1
    assert page.get_by_text("/sensors/{sensor_id}/tare").count() >= 1
    # ReDoc's own "powered by" logo is an image from its CDN; nothing the page needs may be
    assert [kind for kind, _ in refused if kind != "image"] == []
