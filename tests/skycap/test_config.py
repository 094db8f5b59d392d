import dataclasses
from pathlib import Path

import pytest

from skycap.config import ConfigError, load_config, save_config, config_from_args, add_config_args


@dataclasses.dataclass
class Orbit:
    radius_m: float = 8.0
    altitude_m: float = 8.0
    direction: int = 1


@dataclasses.dataclass
class Job:
    name: str = "demo"
    drones: int = 3
    out: Path = Path("flights/x")
    orbit: Orbit = dataclasses.field(default_factory=Orbit)
    tags: list[str] = dataclasses.field(default_factory=list)


def test_defaults_file_and_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('drones = 5\n[orbit]\nradius_m = 10\n')
    cfg = load_config(Job, f, ["orbit.altitude_m=12.5", "name=field", 'tags=["a","b"]'])
    assert cfg.drones == 5 and cfg.orbit.radius_m == 10.0 and cfg.orbit.altitude_m == 12.5
    assert cfg.name == "field" and cfg.tags == ["a", "b"] and cfg.orbit.direction == 1


def test_save_and_reload_is_identical(tmp_path):
    cfg = load_config(Job, None, ["orbit.radius_m=6", "out=/tmp/o"])
    p = save_config(cfg, tmp_path / "out" / "config.toml")
    assert load_config(Job, p) == cfg
    assert isinstance(load_config(Job, p).out, Path)


def test_unknown_key_is_named(tmp_path):
    with pytest.raises(ConfigError, match="orbit.radius"):
        load_config(Job, None, ["orbit.radius=3"])
    f = tmp_path / "c.toml"
    f.write_text("dornes = 2\n")
    with pytest.raises(ConfigError, match="dornes"):
        load_config(Job, f)


def test_wrong_type_names_path_and_fix():
    with pytest.raises(ConfigError) as e:
        load_config(Job, None, ["drones=many"])
    assert "drones" in str(e.value) and "--set" in str(e.value)


def test_missing_and_malformed_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Job, tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("drones = = 3")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(Job, bad)


def test_cli_flags_apply_last():
    import argparse

    p = argparse.ArgumentParser()
    add_config_args(p)
    args = p.parse_args(["--set", "drones=2"])
    cfg = config_from_args(Job, args, {"orbit.radius_m": 4.0, "name": None})
    assert cfg.drones == 2 and cfg.orbit.radius_m == 4.0 and cfg.name == "demo"
