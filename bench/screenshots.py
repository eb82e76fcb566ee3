"""``hitl docs screenshots``: the console in Debian's headless Chromium, on the demo fleet, into ``docs/figures``.

The service is the real one (``create_app`` under uvicorn on 127.0.0.1, the demo configuration with its
own data folder), logged in through the console's form with a fresh operator token. It waits for a
robot to ask for help, then writes:

- ``console-fleet.png``: the fleet overview and the assistance queue;
- ``console-robot.png``: that robot's view, the camera at its gripper: the probe ball, the denoising
  field coloured by mode with the mode means bold, its numbers and U timeline;
- ``console-takeover.png``: the same robot claimed, with the target gizmo and the takeover inputs.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from pathlib import Path

from bench.harness import LocalService
from server.settings import Settings

CHROMIUM = "/usr/bin/chromium"
VIEWPORT = {"width": 1600, "height": 1000}
TIMEOUT_MS = 120_000


def _wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.5)
    raise RuntimeError(f"timed out waiting for {what}")


def take_screenshots(config: Path, out: Path, chromium: str = CHROMIUM, settle_s: float = 8.0) -> list[Path]:
    from playwright.sync_api import sync_playwright

    from server.auth import create_token
    from server.db import make_engine, migrate, session_factory

    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="hitl-screenshots-") as tmp:
        settings = Settings.load(config, data_dir=Path(tmp) / "var")
        settings.data_dir.mkdir(parents=True)
        migrate(settings.db_url)
        engine = make_engine(settings.db_url)
        token = create_token(session_factory(engine), "operator-screenshots", "operator")
        engine.dispose()
        with LocalService(settings, Path(tmp) / "server.log") as svc, sync_playwright() as p:
            fleet = svc.app.state.fleet
            request = _wait(lambda: next(iter(fleet.queue.pending()), None), 300, "a robot to ask for help")
            rid = request.robot_id
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--use-gl=swiftshader"])
            page = browser.new_page(viewport=VIEWPORT)
            page.set_default_timeout(TIMEOUT_MS)
            page.goto(f"{svc.url}/console/login")
            page.fill("#token", token)
            page.click("button[type=submit]")
            page.wait_for_url(f"{svc.url}/console/")
            page.get_by_text("Logged in as").wait_for()
            _dismiss_notifications(page)
            written = []

            page.get_by_role("tab", name="Fleet").click()
            page.get_by_role("button", name=f"Claim robot {rid}").wait_for()
            time.sleep(settle_s)
            written.append(_shot(page, out / "console-fleet.png"))

            page.get_by_role("tab", name="Robot").click()
            page.get_by_role("combobox", name="Robot").click()  # the robot drop-down (the takeover list has one too)
            page.get_by_role("option", name=f"{rid} · ").first.click()
            time.sleep(settle_s)  # the scene builds in a few seconds
            page.get_by_role("button", name="Look at the gripper (F)").click()
            time.sleep(settle_s)
            _dismiss_notifications(page)
            written.append(_shot(page, out / "console-robot.png"))

            page.get_by_role("button", name="Claim (C)").click()
            _wait(lambda: fleet.view(rid).mode == "teleop", 60, f"robot {rid} under teleop")
            time.sleep(settle_s)
            page.get_by_role("button", name="Look at the gripper (F)").click()
            time.sleep(settle_s)
            _dismiss_notifications(page)
            written.append(_shot(page, out / "console-takeover.png"))
            page.get_by_role("button", name="Hand back (R)").click()
            browser.close()
    return written


def _dismiss_notifications(page) -> None:
    """Closes the notifications on screen (e.g. the client's note about software WebGL in this headless run)."""
    for button in page.locator(".mantine-Notification-closeButton").all():
        with contextlib.suppress(Exception):  # gone already
            button.click(timeout=2000)


def _shot(page, path: Path) -> Path:
    page.screenshot(path=str(path))
    return path
