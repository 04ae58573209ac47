"""deploy/'s secure configurations load, and a router from router.secure.json5 with --pki serves
mutual TLS with the ACL on loopback (a client with a certificate of the CA gets through, a
plain TCP client does not)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from bus_agent.config import ConfigError, load_config
from bus_agent.gateway.zenoh_config import make_zenoh_config
from bus_agent.router import RouterConfigError, build_config
from bus_agent.security import pki
from bus_agent.sim.child import free_port

ROOT = Path(__file__).resolve().parents[2]


def test_secure_router_config_with_pki(tmp_path: Path) -> None:
    pki.init(tmp_path)
    pki.issue(tmp_path, "router-h1", ["router"])
    pki.issue(tmp_path, "alice", ["operator"])
    path = str(ROOT / "deploy" / "router.secure.json5")
    with pytest.raises(RouterConfigError, match="--pki"):   # tls/0.0.0.0 without a PKI: refused
        build_config(path)
    ep = f"tls/127.0.0.1:{free_port()}"
    conf, listen, _ = build_config(path, [ep], pki=str(tmp_path), identity="router-h1")
    assert listen == [ep]
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    with zenoh.open(conf):
        with zenoh.open(make_zenoh_config("client", [], [ep], pki=tmp_path, identity="alice")) as s:
            assert s.info.routers_zid()
        with pytest.raises(zenoh.ZError):
            zenoh.open(make_zenoh_config("client", [], [ep.replace("tls/", "tcp/")], connect_timeout_ms=1000))


def test_secure_agent_config_loads(tmp_path: Path) -> None:
    text = (ROOT / "deploy" / "agent.secure.toml").read_text()
    (tmp_path / "a.toml").write_text(text)
    cfg = load_config(tmp_path / "a.toml")
    assert cfg.zenoh.pki == "/etc/zenoh-drives/pki" and cfg.zenoh.identity == cfg.host == "h1"
    assert cfg.with_overrides(host="h2").zenoh.identity == "h2"
    assert all(ep.startswith("tls/") for ep in cfg.zenoh.connect)
    with pytest.raises(ConfigError, match="host name"):
        cfg.with_overrides(identity="alice")
    (tmp_path / "b.toml").write_text(text.replace('listen = []', 'listen = ["tcp/0.0.0.0:7447"]')
                                     .replace('pki = "/etc/zenoh-drives/pki"', ''))
    with pytest.raises(ConfigError, match="--insecure"):
        load_config(tmp_path / "b.toml")
    cfg = load_config(ROOT / "deploy" / "agent.example.toml")
    assert cfg.zenoh.pki is None and cfg.zenoh.insecure is False
