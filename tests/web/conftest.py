"""A real ``hitl serve`` on 127.0.0.1 with a one-robot fleet, and Debian's headless Chromium driven by
playwright (``.ci/run`` installs both; ``playwright install`` is never used)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers import free_port, stop_process

CHROMIUM = os.environ.get("HITL_CHROMIUM", "/usr/bin/chromium")
HITL = [sys.executable, "-m", "hitl.cli"]
RENDER_DPR = 0.25
BROWSER_TIMEOUT_MS = 90_000  # software WebGL on a loaded 2-core box paints about one frame per second

CONFIG = """\
data_dir = "{data}"
control_hz = 10

[controller]
hand_back = "continuous"
cooldown = 10
shadow_signals = ["denoising"]

[queue]
lease_seconds = 60

[[robots]]
task = "lift-hammer"
count = 1
policy = "{policy}"
"""
# The state-based lift policy: on lift-hammer its `choice-stall` asks in the episode's first steps, which these
# tests of the console wait on; the bundled policy that sees did not ask again within their waits after a reset.
# A seeing policy's frames in the console are tested in tests/server/test_cameras.py.
POLICY = Path(__file__).resolve().parents[2] / "policies" / "state" / "lift-cube"


class Served:
    def __init__(self, url: str, tokens: dict[str, str]) -> None:
        self.url, self.tokens = url, tokens

    def api(self, path: str, role: str = "operator", method: str = "GET", json: dict | None = None):
        answer = httpx.request(
            method,
            f"{self.url}/api/v1{path}",
            headers={"Authorization": f"Bearer {self.tokens[role]}"},
            json=json,
            timeout=30,
        )
        answer.raise_for_status()
        return answer.json()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """``hitl serve`` in a subprocess; stopped (SIGTERM) when the module's tests are done."""
    root = tmp_path_factory.mktemp("served")
    config = root / "fleet.toml"
    config.write_text(CONFIG.format(data=root / "var", policy=POLICY))
    tokens = {}
    for role in ("operator", "viewer", "admin"):
        out = subprocess.run(
            [*HITL, "token", "create", "--config", str(config), "--role", role, "--name", f"{role}-browser"],
            check=True,
            capture_output=True,
            text=True,
        )
        tokens[role] = out.stdout.strip().split()[-1]
    port = free_port()
    log = (root / "serve.log").open("w")
    proc = subprocess.Popen(
        [*HITL, "serve", "--config", str(config), "--port", str(port)], stdout=log, stderr=subprocess.STDOUT
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            try:
                if httpx.get(url + "/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert proc.poll() is None, (root / "serve.log").read_text()
            time.sleep(0.5)
        else:
            raise RuntimeError("hitl serve did not become ready:\n" + (root / "serve.log").read_text())
        yield Served(url, tokens)
    finally:
        stop_process(proc)
        log.close()


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).exists(), f"{CHROMIUM} is missing: apt-get install -y chromium (.ci/run does)"
    with sync_playwright() as p:
        chromium = p.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"]
        )
        yield chromium
        chromium.close()


def log_in(browser, served: Served, role: str):
    """A new browser page, logged in through the console's form."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.set_default_timeout(BROWSER_TIMEOUT_MS)
    page.goto(f"{served.url}/console/login")
    page.fill("#token", served.tokens[role])
    page.click("button[type=submit]")
    page.wait_for_url(f"{served.url}/console/")
    # viser's own setting (its client reads it from the URL): the 3D view at a quarter of the page's pixel
    # density. Chromium paints it in software here, and at full density one claimed robot's view kept both
    # cores busy, so that a click waited half a minute for the page to settle
    page.goto(f"{served.url}/console/?fixedDpr={RENDER_DPR}")
    return page
