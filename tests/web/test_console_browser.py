"""The operator's flow in a real browser against a real ``hitl serve``: log in, see the robot in the
queue, claim it, jog it, toggle the gripper with its hotkey, hand it back; and a viewer who watches
read-only. Every effect is checked through the REST API, not through the page."""

import time

from tests.helpers import wait_for
from tests.web.conftest import log_in


def _robot(served):
    return served.api("/robots/0")


def _request(served):
    return next((r for r in served.api("/assistance") if r["robot_id"] == 0), None)


def _unclaimed(served) -> bool:
    """Robot 0 waits in the queue and nobody holds it (one read: the request may close between two)."""
    request = _request(served)
    return request is not None and request["holder"] is None


def test_claim_jog_gripper_and_hand_back_from_the_console(served, browser):
    wait_for(lambda: _request(served) is not None, timeout=120)  # lift-hammer's policy asks at once
    page = log_in(browser, served, "operator")
    page.get_by_role("tab", name="Fleet").click()
    queue_claim = page.get_by_role("button", name="Claim robot 0")
    queue_claim.wait_for()  # the robot is in the queue
    queue_claim.click()
    wait_for(lambda: _robot(served)["mode"] == "teleop", timeout=60)
    assert _request(served)["holder"] == "operator-browser"  # attributed to the logged-in user

    page.get_by_role("tab", name="Robot").click()
    up = page.get_by_role("button", name="+Z (U)")
    wait_for(lambda: up.is_enabled(), timeout=90)
    z0 = _robot(served)["pose"]["position"][2]
    up.hover()
    page.mouse.down()
    # repeats while held: at the control rate on an operator's machine; here Chromium paints the claimed robot's
    # close-up in software (the view frames the gripper on a claim) and the page's repeats come slower
    time.sleep(5.0)
    page.mouse.up()
    wait_for(lambda: _robot(served)["pose"]["position"][2] > z0 + 0.01, timeout=30)

    gap0 = _robot(served)["gripper"]
    page.get_by_text("Logged in as").click()  # focus off any input: hotkeys are for the page
    page.keyboard.press("g")
    wait_for(lambda: _robot(served)["gripper"] < gap0 - 0.01, timeout=30)  # it closes

    page.get_by_role("button", name="Hand back (R)").click()
    wait_for(lambda: _robot(served)["mode"] != "teleop", timeout=30)
    segments = served.api("/segments")
    assert any(s["robot_id"] == 0 and s["operator"] == "operator-browser" for s in segments), segments
    page.close()


def test_a_viewer_watches_read_only(served, browser):
    # a new episode, whose first state asks at once (after a hand-back the robot may not ask again soon)
    served.api("/robots/0/reset", role="admin", method="POST")
    wait_for(lambda: _request(served) is not None and _request(served)["holder"] is None, timeout=120)
    page = log_in(browser, served, "viewer")
    page.get_by_role("tab", name="Fleet").click()
    claim = page.get_by_role("button", name="Claim robot 0")
    claim.wait_for()
    assert claim.is_disabled()
    page.get_by_role("tab", name="Robot").click()
    page.get_by_text("Logged in as").click()
    page.keyboard.press("c")  # the claim hotkey: refused by the service's role check
    page.get_by_text("needs the operator role").first.wait_for()
    assert _request(served)["holder"] is None and _robot(served)["mode"] == "waiting"
    assert page.get_by_role("button", name="+X (I)").is_disabled()
    page.close()


def test_label_a_takeover_from_the_console(served, browser):
    """The robot's recent takeovers with their labels; good, discard and a note set from the page are what
    the REST API then reports, with the console user as who set them."""
    served.api("/robots/0/reset", role="admin", method="POST")
    wait_for(lambda: _request(served) is not None and _request(served)["holder"] is None, timeout=120)
    served.api("/robots/0/claim", method="POST")
    wait_for(lambda: _robot(served)["mode"] == "teleop", timeout=60)
    served.api("/robots/0/command", method="POST", json={"delta_pos": [0.0, 0.0, 0.01], "gripper": -1.0})
    wait_for(lambda: _robot(served)["assisted_steps"] > 0, timeout=60)
    served.api("/robots/0/release", method="POST")
    # this takeover: the newest segment (earlier tests made others), once the hand-back has closed it
    segment = wait_for(lambda: (s := served.api("/segments")[0])["status"] == "closed" and s, 60)
    assert segment["operator"] == "operator-browser" and segment["steps"] > 0

    page = log_in(browser, served, "operator")
    page.get_by_role("tab", name="Robot").click()
    page.get_by_role("cell", name="unlabelled").first.wait_for()  # the takeover, in the list, not yet labelled
    good = page.get_by_role("button", name="Good")
    wait_for(lambda: good.is_enabled(), timeout=90)
    good.click()
    labelled = lambda: next(s for s in served.api("/segments") if s["id"] == segment["id"])  # noqa: E731
    wait_for(lambda: labelled()["label"] == "good", timeout=30)
    assert labelled()["labelled_by"] == "operator-browser"
    page.get_by_role("button", name="Discard").click()
    wait_for(lambda: labelled()["discarded"] is True, timeout=30)
    restore = page.get_by_role("button", name="Restore")
    wait_for(lambda: restore.is_enabled(), timeout=30)  # the list now shows it discarded
    page.get_by_role("cell", name="good, discarded").first.wait_for()
    note = page.get_by_text("Note", exact=True).locator("xpath=following::input[1]")  # viser's label is a sibling
    note.fill("fumbled the grasp, recovered")
    page.get_by_role("button", name="Save note").click()
    wait_for(lambda: labelled()["note"] == "fumbled the grasp, recovered", timeout=30)
    page.close()


def test_follow_the_queue_with_one_key_and_back_to_the_fleet(served, browser):
    """T claims the robot the queue puts first, or says why not (every request held by someone else);
    the fleet table says why the robot waits; the claimed robot's camera views show; a hand-back returns
    the operator to the fleet."""
    served.api("/robots/0/reset", role="admin", method="POST")
    wait_for(lambda: _unclaimed(served), timeout=120)
    page = log_in(browser, served, "operator")
    page.get_by_role("tab", name="Fleet").click()
    reason = _request(served)["reason"]
    page.get_by_role("cell", name=reason[:40]).first.wait_for()  # the fleet table: why it waits, the queue's words
    page.get_by_role("tab", name="Robot").click()

    page.get_by_text("Logged in as").click()  # focus off any input: hotkeys are for the page
    served.api("/robots/0/claim", role="admin", method="POST")  # someone else holds the only request
    wait_for(lambda: _request(served)["holder"] == "admin-browser", timeout=30)
    page.keyboard.press("t")  # within the admin's 60 s lease: no page work between the claim and the key
    page.get_by_text("first in the queue, is held by admin-browser").first.wait_for()  # the refusal, said
    served.api("/robots/0/release", role="admin", method="POST")

    wait_for(lambda: _unclaimed(served), timeout=120)
    page.get_by_text("Logged in as").click()
    page.keyboard.press("t")
    wait_for(lambda: _robot(served)["mode"] == "teleop", timeout=60)
    assert _request(served)["holder"] == "operator-browser"
    page.get_by_text("Following the queue: robot 0").first.wait_for()
    # the claimed robot's cameras, rendered by the service (OSMesa) beside the 3D view
    page.get_by_text("Front and wrist cameras, 160×120 at 2 Hz").first.wait_for()
    assert page.locator("img").count() >= 2
    page.get_by_role("button", name="Hand back (R)").click()
    page.get_by_text("Back to the fleet").first.wait_for()
    page.close()
