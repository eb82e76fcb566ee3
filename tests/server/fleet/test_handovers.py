"""The handover mailbox: claims and releases in order, and the mode they will give a robot."""

from server.fleet.handovers import Handover, HandoverMailbox


def test_the_shown_mode_follows_the_pending_handovers_in_order():
    box = HandoverMailbox()
    assert box.shown_mode("waiting") == "waiting"
    box.put(Handover("claim", "op"))
    assert box.shown_mode("waiting") == "teleop"
    assert box.shown_mode("paused") == "paused" and box.shown_mode("autonomous") == "autonomous"
    box.put(Handover("release", "op"))
    assert box.shown_mode("waiting") == "autonomous"  # claimed, then handed back
    assert [h.kind for h in box.pending()] == ["claim", "release"]
    box.put(Handover("claim", "bob"))
    box.applied(2)  # removed once applied: what came after stays
    assert box.pending() == [Handover("claim", "bob")]
    box.applied(1)
    assert box.pending() == [] and box.shown_mode("teleop") == "teleop"
    box.put(Handover("release", "op"))
    assert box.shown_mode("teleop") == "autonomous" and box.shown_mode("faulted") == "faulted"
