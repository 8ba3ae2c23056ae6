"""The viewer's HTTP routes on a real server: pages, assets and the demo performance."""

from __future__ import annotations

import httpx
import msgpack
import numpy as np
import pytest

from facecast.cli.snapshot import serving
from facecast.rig.demo import demo_animation
from facecast.server.pages.viewer import viewer_dir

BUILT = (viewer_dir() / "dist" / "viewer.js").is_file()


def test_demo_animation_is_the_demo_performance_as_a_wire_array(settings):
    with serving(settings) as base_url:
        response = httpx.get(f"{base_url}/v1/demo/animation")

    body = msgpack.unpackb(response.content)
    points = np.frombuffer(body["points"]["data"], "<f4").reshape(body["points"]["shape"])
    expected = demo_animation(with_vertices=False)
    assert response.headers["content-type"] == "application/vnd.msgpack"
    assert (body["type"], body["fps"], body["points"]["dtype"]) == ("animation", 60.0, "f32")
    np.testing.assert_allclose(points, expected.points, rtol=1e-6, atol=1e-6)


def test_demo_animation_needs_a_token_when_auth_is_on(auth_settings):
    with serving(auth_settings) as base_url:
        anonymous = httpx.get(f"{base_url}/v1/demo/animation")
        viewer = httpx.get(
            f"{base_url}/v1/demo/animation", headers={"Authorization": "Bearer viewer-token"}
        )

    assert (anonymous.status_code, anonymous.json()["code"]) == (401, "unauthorized")
    assert viewer.status_code == 200


@pytest.mark.skipif(not BUILT, reason="the viewer is not built (npm run build in client/viewer)")
@pytest.mark.parametrize("path", ["/viewer", "/overlay"])
def test_pages_load_without_a_token_and_point_at_the_built_script(auth_settings, path):
    with serving(auth_settings) as base_url:
        page = httpx.get(f"{base_url}{path}")
        script = httpx.get(f"{base_url}/viewer/assets/viewer.js")

    assert page.status_code == 200
    assert 'src="viewer/assets/viewer.js"' in page.text
    assert script.status_code == 200
    assert script.headers["content-type"].startswith("text/javascript")


@pytest.mark.parametrize("name", ["package.json", "..%2Fviewer.html", "%2E%2E", "main.js"])
def test_only_built_assets_are_served(settings, name):
    with serving(settings) as base_url:
        response = httpx.get(f"{base_url}/viewer/assets/{name}")

    assert response.status_code == 404
