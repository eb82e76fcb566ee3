"""``docker/``: no container engine runs here, so the files are checked against the repository instead.
The compose file parses; every image is built from a Dockerfile here or is a pinned upstream one; every
command is a ``hitl`` command the CLI accepts, a ``ray start`` with flags the pinned Ray has, or a script
here; every config it names loads; the images install with the README's command (``make install``)."""

import re
import shlex
import tomllib
from pathlib import Path

import pytest
import yaml
from ray.scripts.scripts import start as ray_start

from hitl.cli import build_parser
from server.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker" / "compose.yaml"
UPSTREAM = {"postgres:16-bookworm"}  # images pulled as they are, pinned to a major version and a Debian release


def _compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _dockerfiles() -> dict[str, Path]:
    """Image name -> the Dockerfile that builds it, from the compose file's build sections."""
    out = {}
    for name, svc in _compose()["services"].items():
        if "build" in svc:
            context = (COMPOSE.parent / svc["build"]["context"]).resolve()
            assert context == ROOT, f"{name}: the build context is the repository root"
            path = context / svc["build"]["dockerfile"]
            assert path.is_file(), f"{name}: {path} does not exist"
            out[svc["image"]] = path
    return out


def _instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _check_command(argv: list[str], where: str) -> None:
    exe = argv[0]
    if exe == ".venv/bin/hitl":
        try:
            args = build_parser().parse_args(argv[1:])
        except SystemExit:
            pytest.fail(f"{where}: `{shlex.join(argv)}` is not a command the hitl CLI accepts")
        config = getattr(args, "config", None)
        if config is not None:
            Settings.load(ROOT / config)  # the config exists and validates
    elif exe == ".venv/bin/ray":
        assert argv[1] == "start", f"{where}: only `ray start` is used"
        known = {opt for p in ray_start.params for opt in p.opts}
        for arg in argv[2:]:
            flag = arg.split("=", 1)[0]
            assert flag in known, f"{where}: `ray start` of the pinned Ray has no {flag}"
    else:
        path = ROOT / exe
        assert path.is_file() and path.stat().st_mode & 0o111, f"{where}: {exe} is not an executable file here"


def test_the_compose_file_names_only_images_built_here_or_pinned_upstream():
    built = _dockerfiles()
    assert set(built) == {"hitl-service:latest", "hitl-gpu:latest"}
    for name, svc in _compose()["services"].items():
        assert svc["image"] in built or svc["image"] in UPSTREAM, f"{name}: image {svc['image']} comes from nowhere"
    services = set(_compose()["services"])
    assert {"postgres", "ray-head", "ray-worker", "service", "nightly", "ray-gpu"} <= services


def test_every_command_exists_and_every_config_loads():
    built = _dockerfiles()
    for name, svc in _compose()["services"].items():
        if "command" in svc:
            _check_command(svc["command"], f"compose service {name}")
    for path in built.values():
        for word, rest in _instructions(path):
            if word in ("CMD", "ENTRYPOINT"):
                _check_command(yaml.safe_load(rest), f"{path.name} {word}")


def test_the_images_install_with_the_readmes_command_and_declared_extras():
    extras = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
    makefile = (ROOT / "Makefile").read_text()
    readme = (ROOT / "README.md").read_text()
    assert "make demo" in readme and re.search(r"^demo: install", makefile, re.M)  # the README's set-up installs so
    for path in _dockerfiles().values():
        steps = _instructions(path)
        base = next(rest for word, rest in steps if word == "FROM")
        assert base.startswith("python:3.11-"), f"{path.name}: the project needs Python 3.11, not {base}"
        runs = [rest for word, rest in steps if word == "RUN" and re.search(r"(^|&& )make ", rest)]
        assert len(runs) == 1, f"{path.name}: one `make install` step"
        install = re.search(r"make install EXTRAS=(\S+)", runs[0])
        assert install, f"{path.name}: installs with `make install`, as make demo and make test do"
        assert set(install.group(1).split(",")) <= extras, f"{path.name}: an extra pyproject.toml does not declare"
        assert {"postgres", "ray"} <= set(install.group(1).split(","))  # the compose file's store and workers
        for word, rest in steps:
            if word == "COPY":
                assert rest.split()[0] == ".", f"{path.name}: copies the repository as it is"


def test_the_services_share_one_store_and_the_service_joins_the_cluster():
    services = _compose()["services"]
    url = services["service"]["environment"]["HITL_DATABASE_URL"]
    assert url.startswith("postgresql+psycopg://") and "@postgres:" in url
    assert services["nightly"]["environment"]["HITL_DATABASE_URL"] == url  # the job writes where the fleet reads
    assert services["service"]["volumes"] == services["nightly"]["volumes"]  # and finds its takeovers
    head = services["ray-head"]["command"]
    port = next(a.split("=")[1] for a in head if a.startswith("--port="))
    assert services["service"]["environment"]["JOIN_RAY_CLUSTER"] == f"ray-head:{port}"
    assert Settings.load(ROOT / "configs" / "compose.toml").ray.address == "auto"
    assert "JOIN_RAY_CLUSTER" in (ROOT / "docker" / "entrypoint.sh").read_text()


def test_every_ray_node_authenticates_with_one_token_the_user_sets():
    services = _compose()["services"]
    for name in ("ray-head", "ray-worker", "ray-gpu", "service"):
        env = services[name]["environment"]
        assert env["RAY_AUTH_MODE"] == "token", name
        token = env["RAY_AUTH_TOKEN"]
        assert token.startswith("${RAY_AUTH_TOKEN:?"), f"{name}: the token comes from the user, required"
        assert "$" not in token[2:-1], f"{name}: a literal $ in the message would break compose's interpolation"
