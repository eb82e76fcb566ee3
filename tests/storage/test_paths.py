from pathlib import Path

from storage.paths import DATA_ROOT_ENV, data_root, portable, resolve


def test_paths_under_the_data_root_are_recorded_relative(tmp_path, monkeypatch):
    monkeypatch.setenv(DATA_ROOT_ENV, str(tmp_path))
    demos = tmp_path / "data" / "demos" / "lift-cube"
    assert portable(demos) == "data/demos/lift-cube"
    assert resolve("data/demos/lift-cube") == demos
    assert data_root() == tmp_path


def test_a_relative_path_is_taken_from_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.delenv(DATA_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    assert portable("data/../data/demos") == "data/demos"
    assert resolve(portable("data/demos")) == tmp_path / "data" / "demos"


def test_a_path_outside_the_data_root_stays_absolute(tmp_path, monkeypatch):
    root, other = tmp_path / "root", tmp_path / "elsewhere" / "demos"
    root.mkdir()
    monkeypatch.setenv(DATA_ROOT_ENV, str(root))
    assert portable(other) == other.as_posix() and Path(portable(other)).is_absolute()
    assert resolve(other) == other  # absolute paths are opened as they are
    assert portable(root / ".." / "elsewhere" / "demos") == other.as_posix()  # no ../ escapes recorded
