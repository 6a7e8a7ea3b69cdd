"""The `lsgan serve` page in headless Chromium, driven as a person would use it, against a real server.

A real ``lsgan serve`` (the CLI, in a subprocess on a free loopback port: tests/serve_client.py) serves conftest's
tiny trained models (``serve_models``); then tools/three-check/serve-page.mjs loads the page, types a sentence,
clicks Generate, waits until the viewer plays, clicks the downloads, pauses, orbits and zooms the view, and reports
what it saw as JSON: requests, failed requests, console errors, the frames the viewer showed, the latency line, the
download links and files. We assert on that report and on its screenshot
(``$LSGAN_ARTIFACTS/serve-page.png`` or ``tests/artifacts/serve-page.png``, git-ignored), which must show the
bones in the previews' left (blue) and right (red) colours.

Needs Debian's Chromium (``apt-get install -y chromium chromium-driver``) and ``npm ci`` in tools/three-check, as
tests/test_export_browser.py does; without them the tests skip.
"""
from __future__ import annotations

import json
import os
import subprocess
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from serve_client import THREE_CHECK, Server, missing_browser

DRIVER = THREE_CHECK / "serve-page.mjs"
ARTIFACTS = Path(os.environ.get("LSGAN_ARTIFACTS") or Path(__file__).resolve().parent / "artifacts")
SENTENCE = "a person walks forward"
API_KEY = "page-test-key"


# Decided at import, so that a machine without the browser skips before conftest trains the models.
pytestmark = [pytest.mark.slow, pytest.mark.skipif(missing_browser() is not None, reason=str(missing_browser()))]


def url_of(server: Server) -> str:
    return f"http://127.0.0.1:{server.port}/"


@pytest.fixture(scope="module")
def server(serve_models: Path):
    """conftest's tiny text GAN, served by the real CLI."""
    s = Server("--gan", "gan", "--vae", "vae", cwd=serve_models)
    yield s
    assert s.stop() == 0, s.stderr


def drive(url: str, *args: str, timeout: float = 120) -> dict:
    """Run serve-page.mjs; its JSON report, with the exit status as ``returncode`` and stderr as ``stderr``."""
    out = subprocess.run(["node", str(DRIVER), "--url", url, "--timeout", str(timeout), *args],
                         capture_output=True, text=True, timeout=timeout + 30, cwd=THREE_CHECK)
    assert out.stdout.strip(), f"serve-page.mjs printed no report ({out.returncode}):\n{out.stderr}"
    report = json.loads(out.stdout.strip().splitlines()[-1])
    report.update(returncode=out.returncode, stderr=out.stderr)
    return report


def assert_only_own_origin(report: dict, url: str) -> None:
    origin = url.rstrip("/")
    assert report["requests"], "the page made no request"
    outside = [r for r in report["requests"] if not r.split(" ", 1)[1].startswith(origin + "/")]
    assert not outside, f"the page loaded from outside the server: {outside}"
    assert report["outside_requests"] == []


def colour_counts(png: Path, box: dict) -> dict[str, int]:
    """Pixels of the canvas region that are clearly blue, red, orange (a drawn path), or anything but near-white."""
    from PIL import Image

    with Image.open(png) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.int32)
    x0, y0 = int(box["x"]), int(box["y"])
    view = rgb[y0:y0 + int(box["height"]), x0:x0 + int(box["width"])]
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    return {"blue": int(((b > 150) & (b - r > 80) & (b - g > 60)).sum()),
            "orange": int(((r > 180) & (g > 80) & (g < 170) & (b < 90)).sum()),
            "red": int(((r > 150) & (r - g > 80) & (r - b > 80)).sum()),
            "ink": int((view.max(axis=-1) < 200).sum())}


def test_page_generates_plays_and_downloads(server: Server) -> None:
    screenshot = ARTIFACTS / "serve-page.png"
    screenshot.unlink(missing_ok=True)
    report = drive(url_of(server), "--text", SENTENCE, "--screenshot", str(screenshot))

    assert report["returncode"] == 0 and report["problems"] == [], \
        f"{report['problems']}\n{report['stderr']}\nserver log:\n{server.stderr[-4000:]}"
    assert report["console_errors"] == [] and report["page_errors"] == []
    assert report["failed_requests"] == []
    assert_only_own_origin(report, url_of(server))

    assert report["state"] == "playing"
    samples = report["frame_samples"]
    assert len(set(samples)) >= 3, f"the viewer's frame did not advance: {samples}"
    assert report["viewer"]["frames"] >= 4 and report["viewer"]["playing"] is True
    assert "Round trip" in report["latency_text"] and " ms" in report["latency_text"]

    links = report["downloads"]
    motion = links["glb"].removeprefix("/v1/motions/").removesuffix(".glb")
    assert links == {"glb": f"/v1/motions/{motion}.glb", "bvh": f"/v1/motions/{motion}.bvh"}
    saved = report["saved"]
    assert saved["glb"]["head"].startswith("glTF") and saved["glb"]["bytes"] > 1000
    assert saved["bvh"]["head"].startswith("HIERARCHY") and saved["bvh"]["bytes"] > 1000

    assert report["interaction"] == {"paused": True, "drag_changed_view": True, "wheel_changed_view": True,
                                     "frame_held": True, "resumed": True}

    assert screenshot.exists() and screenshot.stat().st_size > 10_000, "the screenshot is missing or blank"
    counts = colour_counts(screenshot, report["canvas_box"])
    assert counts["blue"] > 150 and counts["red"] > 150, f"no left/right bones in the view: {counts}"


def test_page_draws_a_path_and_continues_the_motion(server: Server) -> None:
    """Draw a path as a person would (press "Draw a path", drag up the view then right), generate: the page sends
    one point per frame along the drag (up the screen is away from the camera, +z; right is -x, as the view shows
    them), and the figure's root passes within 3 cm of every one. Then tick "continue the motion shown" and
    generate again: the new motion starts where the first ends. The screenshot shows the drawn path in orange."""
    screenshot = ARTIFACTS / "serve-page-path.png"
    screenshot.unlink(missing_ok=True)
    report = drive(url_of(server), "--text", SENTENCE, "--frames", "60", "--draw", "0,-90 80,-90", "--continue",
                   "--no-download", "--screenshot", str(screenshot))
    assert report["returncode"] == 0 and report["problems"] == [], \
        f"{report['problems']}\n{report['stderr']}\nserver log:\n{server.stderr[-4000:]}"
    assert report["failed_requests"] == [] and report["console_errors"] == []

    path, root = np.array(report["sent_path"]), np.array(report["root"])
    assert path.shape == (60, 2) and root.shape == (60, 3) and np.abs(path[0]).max() == 0
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    assert 0.8 < steps.sum() < 4 and steps.std() < 0.01, "not evenly spaced along a drag of a metre or two"
    corner = int(np.argmax(path[:, 1]))  # the drag's turn: away first (+z), then to the screen's right (-x)
    assert path[corner, 1] > 0.4 and abs(path[corner, 0]) < 0.05 and path[-1, 0] < -0.3
    assert np.linalg.norm(root[:, [0, 2]] - path, axis=1).max() < 0.03, "the figure's root leaves the drawn path"
    assert "m/s" in report["drag"]["path_line"] and "path missed by" not in report["latency_text"]
    assert report["sent_facing"] is True  # "face along the path" is ticked by default

    first, then = np.array(report["last_poses"]), np.array(report["continued_poses"])
    assert report["continue_from"] and report["continue_sent_path"] is None and report["placement"]
    assert first.shape == then.shape == (5, 22, 3) and np.abs(then - first).max() < 0.03, "the continuation does not start where the motion ends"
    assert "keyframes by" in report["latency_text"]
    counts = colour_counts(screenshot, report["canvas_box"])
    assert counts["orange"] > 100, f"the drawn path is not in the view: {counts}"


def test_page_shows_the_servers_error(server: Server) -> None:
    """Empty text, sent with Enter in the text box: the server's one-line 4xx message is shown and the state is
    "error"; the refused request and Chromium's line about it are the only failures."""
    screenshot = ARTIFACTS / "serve-page-error.png"
    report = drive(url_of(server), "--text", "", "--enter", "--expect-error", "--screenshot", str(screenshot))

    assert report["returncode"] == 0 and report["problems"] == [], f"{report['problems']}\n{report['stderr']}"
    assert report["state"] == "error" and report["page_errors"] == []
    failed = report["failed_requests"]
    assert len(failed) == 1 and failed[0]["method"] == "POST" and failed[0]["url"] == url_of(server) + "v1/generate"
    assert 400 <= failed[0]["status"] < 500
    assert all(text.startswith(f"Failed to load resource: the server responded with a status of {failed[0]['status']}")
               for text in report["console_errors"]), report["console_errors"]

    # The page shows exactly what the API said.
    request = urllib.request.Request(url_of(server) + "v1/generate", data=json.dumps({"text": ""}).encode(),
                                     headers={"Content-Type": "application/json"}, method="POST")
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=30)
    expected = json.loads(refused.value.read())["error"]
    assert report["error_text"].strip() == expected and "\n" not in expected
    assert_only_own_origin(report, url_of(server))


def test_page_asks_for_the_api_key(serve_models: Path) -> None:
    """With --api-key the first Generate is refused (401); the page asks for the key, sends it as a bearer token
    and fetches the downloads with it (fetch + blob, since a link cannot carry the header)."""
    keyed = Server("--gan", "gan", "--vae", "vae", "--api-key", API_KEY, cwd=serve_models)
    try:
        report = drive(url_of(keyed), "--text", SENTENCE, "--api-key", API_KEY,
                       "--screenshot", str(ARTIFACTS / "serve-page-key.png"))
    finally:
        assert keyed.stop() == 0, keyed.stderr
    assert report["returncode"] == 0 and report["problems"] == [], f"{report['problems']}\n{report['stderr']}"
    assert report["error_before_key"].strip(), "no message asked for the key"
    assert {f["status"] for f in report["failed_requests"]} == {401}
    assert report["state"] == "playing" and len(set(report["frame_samples"])) >= 3
    assert report["saved"]["glb"]["head"].startswith("glTF") and report["saved"]["bvh"]["head"].startswith("HIERARCHY")
    assert_only_own_origin(report, url_of(keyed))


def test_page_offers_the_actions_of_an_action_model(serve_models: Path) -> None:
    """An action GAN: the page shows a list of the model's actions instead of the text box."""
    action_server = Server("--gan", "act-gan", "--vae", "vae", cwd=serve_models)
    try:
        status, info = action_server.json("GET", "/v1/info")
        assert status == 200 and info["condition"] == "action" and info["actions"]
        report = drive(url_of(action_server), "--action", info["actions"][-1], "--frames", "40",
                       "--screenshot", str(ARTIFACTS / "serve-page-action.png"))
    finally:
        assert action_server.stop() == 0, action_server.stderr
    assert report["returncode"] == 0 and report["problems"] == [], f"{report['problems']}\n{report['stderr']}"
    assert report["viewer"]["frames"] == 40 and len(set(report["frame_samples"])) >= 3
    assert report["console_errors"] == [] and report["failed_requests"] == []
