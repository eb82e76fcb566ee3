import os

import numpy as np
import pytest

from sim.registry import make_task


def pytest_configure(config):
    """Under ``pytest -n N`` (``make test``) the workers share the machine's cores: torch computes on one
    thread in each, as oversubscribed OpenMP threads spin against each other (a 6 s training test took
    two minutes beside another worker). Processes the tests start set their own threads."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


# The longest test files (``make test``'s durations), run first: ``--dist loadfile`` hands each worker the next
# file when it is free, so a long file that comes last in collection order (tests/web sorts last) leaves the
# other worker idle at the end. Longest first balances the two workers (`make test` passes
# --no-loadscope-reorder, as xdist would otherwise order files by their number of tests).
LONGEST_FIRST = (
    "tests/web/test_console_browser.py",
    "tests/server/finetune/test_finetune.py",
    "tests/bench/test_nights.py",
    "tests/server/test_server_faults.py",
    "tests/server/test_runtime.py",
    "tests/server/test_fuzz.py",
    "tests/bench/test_hitl_service.py",
    "tests/bench/test_uncertainty.py",
    "tests/server/test_workers.py",
    "tests/bench/test_fleet.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable: the rest keep order


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


def _pg_bin(name: str) -> str:
    import glob
    import shutil

    found = shutil.which(name) or next(iter(sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)), None)
    if found is None:
        raise RuntimeError(f"PostgreSQL's {name} not found: apt-get install -y postgresql (.ci/run does)")
    return found


@pytest.fixture(scope="session")
def postgres_url():
    """A throwaway PostgreSQL cluster on 127.0.0.1 (initdb into a temporary folder, trust auth), stopped
    and removed at the end of the session; run as ``nobody`` when the tests run as root (postgres refuses
    root)."""
    import os
    import shutil
    import subprocess
    import tempfile

    from tests.helpers import free_port

    root = tempfile.mkdtemp(prefix="hitl-pg-")
    as_user = ["runuser", "-u", "nobody", "--"] if os.geteuid() == 0 else []
    if as_user:
        shutil.chown(root, "nobody")
    data, port = os.path.join(root, "data"), free_port()
    run = lambda *cmd: subprocess.run([*as_user, *cmd], check=True, capture_output=True, timeout=120)  # noqa: E731
    run(_pg_bin("initdb"), "-D", data, "-A", "trust", "-U", "hitl")
    opts = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off"
    run(_pg_bin("pg_ctl"), "-D", data, "-o", opts, "-l", os.path.join(root, "log"), "-w", "start")
    try:
        run(_pg_bin("createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "hitl", "hitl")
        yield f"postgresql+psycopg://hitl@127.0.0.1:{port}/hitl"
    finally:
        subprocess.run([*as_user, _pg_bin("pg_ctl"), "-D", data, "-m", "immediate", "stop"], capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="session")
def ray_local():
    """A local Ray instance for the session (the ``ray`` back end's tests): 2 CPUs, no dashboard; the
    service's ``server.ray_cluster.connect`` finds it initialized and uses it."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, namespace="hitl-tests", log_to_driver=False)
    yield ray
    ray.shutdown()
