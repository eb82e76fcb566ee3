from pathlib import Path

import pytest
from pydantic import ValidationError

from hitl.cli import main
from policy.controller import ControllerConfig
from server.auth import Principal, authenticate, create_token, revoke_token
from server.db import make_engine, migrate, session_factory
from server.settings import REMOVED, ControllerSettings, Settings, bundled_policy, env_name


def test_settings_come_from_the_file_with_environment_and_flags_on_top(tmp_path, monkeypatch):
    config = tmp_path / "fleet.toml"
    config.write_text('port = 9001\ncontrol_hz = 5\n[[robots]]\ntask = "cup-stack"\ncount = 2\n')
    s = Settings.load(config)
    assert s.port == 9001 and s.control_hz == 5 and s.robots[0].count == 2
    assert s.robots[0].policy_dir == bundled_policy("cup-stack") and s.robots[0].policy_dir.is_dir()
    monkeypatch.setenv("HITL_PORT", "9002")
    monkeypatch.setenv("DATABASE_URL", "sqlite:////tmp/elsewhere.db")
    s = Settings.load(config)
    assert s.port == 9002 and s.db_url == "sqlite:////tmp/elsewhere.db" and s.control_hz == 5
    assert Settings.load(config, port=9003).port == 9003  # command-line flags win


def test_a_variable_set_to_none_unsets_what_the_file_sets(tmp_path, monkeypatch):
    config = tmp_path / "fleet.toml"
    config.write_text('[controller]\nhand_back = "continuous"\nreturn_after = 3\nwatchdog = 0.8\n')
    assert Settings.load(config).controller.return_after == 3
    monkeypatch.setenv("HITL_CONTROLLER__RETURN_AFTER", "none")  # as `--set controller.return_after=none` gives it
    monkeypatch.setenv("HITL_CONTROLLER__WATCHDOG", "none")
    s = Settings.load(config).controller
    assert s.return_after is None and s.watchdog is None and s.hand_back == "continuous"  # the file's others stay
    monkeypatch.setenv("HITL_CONTROLLER__RETURN_AFTER", "nothing")
    with pytest.raises(ValueError, match="return_after"):
        Settings.load(config)


def test_a_section_merges_key_by_key_from_the_file_the_environment_and_the_flags(tmp_path, monkeypatch):
    config = tmp_path / "fleet.toml"
    config.write_text("[controller]\nbudget = 8\ncooldown = 3\n[queue]\nlease_seconds = 30\n")
    monkeypatch.setenv("HITL_CONTROLLER__COOLDOWN", "5")
    s = Settings.load(config, controller={"watchdog": 0.5})
    assert (s.controller.budget, s.controller.cooldown, s.controller.watchdog) == (8, 5, 0.5)
    assert s.queue.lease_seconds == 30 and s.queue.order == "priority"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("port = [", "invalid TOML"),
        ("bogus = 1", "bogus"),
        ('[[robots]]\ntask = "lift-banana"', "unknown task 'lift-banana'"),
        ("control_hz = -1", "control_hz"),
        ('[controller]\nsignal = "vibes"', "unknown signal 'vibes'"),
        ("[controller]\nbudget = 0", "budget"),
        ("[controller]\nwatchdog = 1.0", "watchdog"),
        ("[controller]\nbogus = 1", "bogus"),
        ("[cameras]\nhz = 0", "hz"),
        ('[queue]\norder = "lifo"', "order"),
        ("robots = []", "at least one robot"),
        ("[finetune]\ntakeover_tail = 0", "takeover_tail"),
        (
            '[[robots]]\ntask = "lift-cube"\npolicy = "a/lift-cube"\n'
            '[[robots]]\ntask = "lift-nut"\npolicy = "b/lift-cube"',
            "two policy folders named 'lift-cube'",
        ),
    ],
)
def test_bad_config_files_get_errors_that_name_the_problem(tmp_path, text, match):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    with pytest.raises(ValueError, match=match):
        Settings.load(config)


def test_groups_may_share_one_policy_folder():
    same = Settings(robots=[{"task": "lift-cube", "count": 2}, {"task": "lift-nut"}, {"task": "open-drawer"}])
    assert same.robots[0].policy_dir == same.robots[1].policy_dir  # the bundled lift policy, one lineage


def test_the_cli_reports_a_bad_config_without_a_traceback(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text("[controller]\nbudget = 0")
    assert main(["serve", "--config", str(config)]) == 2
    assert "budget" in capsys.readouterr().err
    config.write_text("budget = 4")
    assert main(["serve", "--config", str(config)]) == 2
    assert f"setting 'budget' in {config} was renamed: use 'controller.budget'" in capsys.readouterr().err
    assert main(["serve", "--config", str(tmp_path / "missing.toml")]) == 2
    capsys.readouterr()
    assert main(["finetune", "--data-dir", str(tmp_path / "var"), "--takeover-tail", "-1", "--quiet"]) == 2
    assert "takeover tail must be an integer >= 1 or None, got -1" in capsys.readouterr().err


def test_a_removed_name_is_refused_naming_the_new_one(tmp_path, monkeypatch):
    config = tmp_path / "old.toml"
    for old, new in REMOVED.items():
        config.write_text(f"{old} = 1\n")
        with pytest.raises(ValueError, match=f"setting '{old}' in .*old.toml was renamed: use '{new}'"):
            Settings.load(config)
        with pytest.raises(ValueError, match=f"setting '{old}' in the overrides was renamed: use '{new}'"):
            Settings.load(None, **{old: 1})
        with pytest.raises(ValueError, match=f"was renamed: use '{new}'"):
            Settings(**{old: 1})
        monkeypatch.setenv(f"HITL_{old.upper()}", "1")
        with pytest.raises(
            ValueError, match=f"'HITL_{old.upper()}' in the environment was renamed: use '{env_name(new)}'"
        ):
            Settings()
        monkeypatch.delenv(f"HITL_{old.upper()}")
    assert Settings().controller.budget == 4  # nothing left behind
    assert env_name("controller.budget") == "HITL_CONTROLLER__BUDGET"


def test_every_new_name_is_a_setting_and_no_old_one_is():
    for new in set(REMOVED.values()):
        section, key = new.split(".")
        assert key in type(getattr(Settings(), section)).model_fields, new
    assert not (set(REMOVED) - {"cameras", "inference"}) & set(Settings.model_fields)  # those two are sections now


def test_the_controller_section_is_the_controllers_config_with_the_signals():
    s = Settings(
        controller={"hand_back": "continuous", "budget": 9, "return_after": 4, "cooldown": 0, "resume": "history"}
    )
    expected = ControllerConfig(hand_back="continuous", budget=9, return_after=4, cooldown=0, resume="history")
    assert s.controller.config() == expected and type(s.controller.config()) is ControllerConfig
    assert set(ControllerSettings.model_fields) - set(ControllerConfig.model_fields) == {"signal", "shadow_signals"}
    for name, field in ControllerConfig.model_fields.items():  # each bound declared once: the same field object
        assert ControllerSettings.model_fields[name].metadata == field.metadata, name
    c = Settings().controller
    assert (c.resume, c.budget, c.cooldown, c.return_after) == ("restart", 4, 10, None)
    with pytest.raises(ValidationError, match="budget"):
        ControllerConfig(budget=0)


def test_set_flags_name_a_sections_key():
    from hitl.server_commands import _settings_env

    assert _settings_env(["controller.budget=8", "port=9000"]) == {"HITL_CONTROLLER__BUDGET": "8", "HITL_PORT": "9000"}
    with pytest.raises(ValueError, match="setting 'budget' in --set was renamed: use 'controller.budget'"):
        _settings_env(["budget=8"])
    with pytest.raises(ValueError, match="KEY=VALUE"):
        _settings_env(["controller.=8"])


@pytest.mark.parametrize("source", ["toml", "env", "keyword", "constructor"])
def test_a_removed_name_beside_its_new_one_is_refused_too(tmp_path, monkeypatch, source):
    config = tmp_path / "both.toml"
    config.write_text("budget = 4\n[controller]\nbudget = 4\n" if source == "toml" else "")
    if source == "env":
        monkeypatch.setenv("HITL_BUDGET", "4")
        monkeypatch.setenv("HITL_CONTROLLER__BUDGET", "4")
    old, new = ("HITL_BUDGET", "HITL_CONTROLLER__BUDGET") if source == "env" else ("budget", "controller.budget")
    with pytest.raises(ValueError, match=f"setting {old!r}.* was renamed: use {new!r}"):
        if source == "constructor":
            Settings(budget=4, controller={"budget": 4})
        else:
            Settings.load(config, **({"budget": 4, "controller": {"budget": 4}} if source == "keyword" else {}))


def test_tokens_are_stored_hashed_and_can_be_revoked(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    migrate(url)
    migrate(url)  # idempotent
    sessions = session_factory(make_engine(url))
    token = create_token(sessions, "alice", "operator")
    assert authenticate(sessions, token) == Principal("alice", "operator")
    assert authenticate(sessions, token + "x") is None and authenticate(sessions, None) is None
    stored = b"".join(p.read_bytes() for p in tmp_path.glob("db.sqlite*"))  # the database and its WAL
    assert token.encode() not in stored and b"alice" in stored
    with pytest.raises(ValueError, match="already exists"):
        create_token(sessions, "alice", "viewer")
    with pytest.raises(ValueError, match="role"):
        create_token(sessions, "bob", "root")
    assert Principal("a", "admin").has("operator") and not Principal("v", "viewer").has("operator")
    assert revoke_token(sessions, "alice") and authenticate(sessions, token) is None


def test_the_jobs_takeover_selection_comes_from_settings_with_flags_on_top():
    from hitl.cli import build_parser
    from hitl.registry_commands import _finetune_config

    settings = Settings(finetune={"successful_only": True, "takeover_tail": 33})

    def config(*flags):
        return _finetune_config(build_parser().parse_args(["finetune", *flags]), settings)

    assert (config().successful_only, config().takeover_tail) == (True, 33)
    assert config("--takeover-tail", "20").takeover_tail == 20
    assert config("--takeover-tail", "0").takeover_tail is None  # every step again
    assert config("--no-successful-only").successful_only is False
    assert _finetune_config(build_parser().parse_args(["finetune"]), Settings()).selection.tail is None


def test_half_the_demo_fleet_is_in_distribution_and_each_problem_type_has_a_robot():
    """``make demo``: at least half the robots on their policy's training task, and each of
    the three problem types present, so a new user sees both."""
    settings = Settings.load(Path(__file__).resolve().parents[2] / "configs" / "demo.toml")
    counts = {g.task: g.count for g in settings.robots}
    assert 2 * counts.get("lift-cube", 0) >= sum(counts.values())
    assert any(t in counts for t in ("lift-nut", "lift-hammer", "lift-hook"))  # distribution shift
    assert "cup-stack" in counts and "open-drawer" in counts  # partial observability, multimodality


def test_the_ray_config_is_the_demo_fleet_on_ray_actors():
    configs = Path(__file__).resolve().parents[2] / "configs"
    demo, ray = Settings.load(configs / "demo.toml"), Settings.load(configs / "ray.toml")
    assert ray.workers.kind == "ray" and demo.workers.kind != "ray" and ray.ray.address is None  # a local instance
    same = {"workers", "ray"}
    assert ray.model_dump(exclude=same) == demo.model_dump(exclude=same)


def test_ray_settings_are_validated():
    with pytest.raises(ValidationError):
        Settings(workers={"kind": "ray"}, ray={"cpus_per_actor": 0})
    with pytest.raises(ValidationError):
        Settings(workers={"kind": "ray"}, ray={"namespace": ""})


def test_the_ray_back_end_without_ray_installed_is_refused_at_load(monkeypatch):
    monkeypatch.setattr("server.ray_cluster.ray_available", lambda: False)
    with pytest.raises(ValidationError, match=r"pip install '.\[ray\]'"):
        Settings(workers={"kind": "ray"})
    assert Settings(workers={"kind": "pool"}).workers.kind == "pool"  # the others need nothing more
