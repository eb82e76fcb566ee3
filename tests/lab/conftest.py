import pytest


@pytest.fixture(autouse=True)
def lab_signals():
    """The lab's signals registered, as ``hitl``'s benchmark commands have them, and gone after the test."""
    from lab.signals import registered

    with registered():
        yield
