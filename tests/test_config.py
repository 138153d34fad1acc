"""Configuration: defaults, the shipped files, and bad settings named at start."""

from __future__ import annotations

import tomllib

import pytest

from common.config import DEFAULTS, FREE_FORM_SECTIONS, ConfigError, default_config_path, load_config


def test_station_toml_states_exactly_the_embedded_defaults():
    assert load_config(default_config_path()) == load_config(None)


def test_station_toml_writes_out_every_fixed_setting():
    # the file is the reference a lab copies: a setting only in code is one nobody finds
    stated = tomllib.loads(default_config_path().read_text())
    missing = [f"{section}.{key}" for section, values in DEFAULTS.items() if section not in FREE_FORM_SECTIONS
               for key in values if key not in stated.get(section, {})]
    assert missing == []


def test_lab_toml_loads_with_several_hosts_and_nfs_storage():
    cfg = load_config(default_config_path().with_name("lab.toml"))
    assert cfg["storage"]["file_locking"] is False and cfg["storage"]["create_root"] is False
    assert cfg["broker"]["host"] != "127.0.0.1"
    assert cfg["routing"]["rgbn.ready"] == ["features", "renderer"]
    # the proposal store stays on the share, where the bench's review page reads it: not in WAL, which NFS cannot
    # hold (docs/storage.md)
    assert "db" not in cfg["services"]["matcher"] and cfg["services"]["matcher"]["journal_mode"] == "DELETE"


def test_missing_settings_take_defaults(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[broker]\nport = 7000\n")
    cfg = load_config(p)
    assert cfg["broker"]["port"] == 7000
    assert cfg["broker"]["feed_port"] == DEFAULTS["broker"]["feed_port"]
    assert cfg["routing"] == DEFAULTS["routing"]


@pytest.mark.parametrize("text, key", [
    ("[broker]\nport = 'abc'\n", "broker.port"),
    ("[broker]\nprot = 5555\n", "broker.prot"),
    ("[brokr]\nport = 5555\n", "brokr"),
    ("[broker]\nport = 70000\n", "broker.port"),
    ("[broker]\nheartbeat_interval_s = 0\n", "broker.heartbeat_interval_s"),
    ("[broker]\nfeed_port = 5555\n", "broker.feed_port"),
    ("[storage]\nfile_locking = 'no'\n", "storage.file_locking"),
    ("[routing]\n'no.such' = ['solver']\n", "routing.no.such"),
    ("[routing]\n'rgbn.ready' = 'features'\n", "routing.rgbn.ready"),
    ("[scanner]\ndevice = 'usb'\n", "scanner.device"),
    ("[scanner]\ndepth = 12\n", "scanner.depth"),
    ("[services]\nsolver = 3\n", "services.solver"),
    ("[broker\nport = 1\n", "TOML syntax"),
])
def test_bad_config_fails_at_start_naming_the_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(p)


def test_unreadable_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml"):
        load_config(tmp_path / "nope.toml")


def test_service_sections_are_free_form_and_overrides_apply(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[services.solver]\nrobust = true\nmax_iter = 20\n")
    cfg = load_config(p, {"services.solver.max_iter": 40, "broker.max_attempts": 5})
    assert cfg["services"]["solver"] == {"robust": True, "max_iter": 40}
    assert cfg["broker"]["max_attempts"] == 5
    with pytest.raises(ConfigError, match="broker.nothing"):
        load_config(None, {"broker.nothing": 1})
