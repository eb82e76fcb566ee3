import numpy as np
import pytest

from sim.registry import make_task


@pytest.fixture(scope="session")
def task_cache():
    """One simulator per task for the whole session: building one costs seconds."""
    tasks = {}

    def get(name: str):
        if name not in tasks:
            tasks[name] = make_task(name)
        return tasks[name]

    yield get
    for t in tasks.values():
        t.close()


@pytest.fixture
def rng():
    return np.random.default_rng(0)
