"""The demo's security set-up without a flight: secure by default (a temporary fleet CA, tls endpoints, every child
given the fleet folder), ``--insecure`` loud in the log and in the summary, a given fleet folder checked first."""

from __future__ import annotations

import logging

import pytest

from apps.demo import DemoConfig, _fleet_keys, _network, _security_report
from comms.security import FleetKeys, SecurityError
from skycap.errors import SkycapError


def test_secure_by_default_with_a_temporary_fleet_ca(tmp_path):
    cfg = DemoConfig(zenoh_endpoint="tcp/127.0.0.1:7999")
    fk, temporary = _fleet_keys(cfg, ["drone_1", "drone_2"])
    try:
        assert temporary and set(fk.identities) == {"gcs", "sim", "drone_1", "drone_2"}
        endpoint, args = _network(cfg, fk)
        assert endpoint == "tls/127.0.0.1:7999"
        assert args == ["--zenoh-connect", endpoint, "--zenoh-keys", str(fk.folder)]
        rep = _security_report(fk, temporary)
        assert rep["insecure"] is False and "temporary" in rep["keys"]
    finally:
        import shutil
        shutil.rmtree(fk.folder.parent)


def test_insecure_is_loud_and_reported(caplog):
    cfg = DemoConfig(insecure=True)
    with caplog.at_level(logging.WARNING):
        fk, temporary = _fleet_keys(cfg, ["drone_1"])
    assert fk is None and not temporary
    assert "INSECURE demo" in caplog.text
    endpoint, args = _network(cfg, None)
    assert endpoint.startswith("tcp/") and "--zenoh-keys" not in args
    assert _security_report(None, False)["insecure"] is True


def test_a_given_fleet_folder_must_be_the_demos_fleet_and_hold_every_identity(tmp_path):
    FleetKeys.create(tmp_path / "a", "other", drones=["drone_1"], sim=True)
    with pytest.raises(SkycapError, match="fleet 'other'"):
        _fleet_keys(DemoConfig(keys_dir=str(tmp_path / "a")), ["drone_1"])
    FleetKeys.create(tmp_path / "b", "demo", drones=["drone_1"], sim=True)
    with pytest.raises(SecurityError, match="drone_2"):
        _fleet_keys(DemoConfig(keys_dir=str(tmp_path / "b")), ["drone_1", "drone_2"])
    fk, temporary = _fleet_keys(DemoConfig(keys_dir=str(tmp_path / "b")), ["drone_1"])
    assert not temporary and fk.folder == tmp_path / "b"
