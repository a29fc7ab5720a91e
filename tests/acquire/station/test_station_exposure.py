"""A station listener other hosts can reach is protected by Zenoh itself (mTLS, access control
or user-password authentication) or explicitly declared open; else it does not start."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from acquire.live.bus import BusConfigError
from acquire.station.config import StationConfig, flat_paths, load_station_config
from acquire.station.service import Station
from calib.io.yamlfile import ConfigError
from tests.acquire.daemon_harness import free_port

ROOT = Path(__file__).resolve().parents[3]
TOKEN = "Zk3-pQ9xT2mV7bN4cR8sW1yL6hJ0fG"


def _config(tmp_path: Path, zenoh_yaml: str) -> Path:
    cfg = tmp_path / "station.yaml"
    cfg.write_text(f"archive: archive\ntoken_file: station.token\nzenoh:\n{zenoh_yaml}")
    return cfg


MTLS = ("  zenoh:\n    transport/link/tls: {root_ca_certificate: ca.pem, listen_certificate: s.pem,\n"
        "                         listen_private_key: s.key, enable_mtls: true}\n")


@pytest.mark.parametrize("zenoh_yaml", [
    "  listen: [tcp/127.0.0.1:7447, unixsock-stream//run/remaster/station.sock]\n",
    "  listen: [tls/0.0.0.0:7447]\n" + MTLS,
    "  listen: [tcp/0.0.0.0:7447]\n  zenoh: {access_control: {enabled: true, default_permission: deny}}\n",
    "  listen: [tcp/0.0.0.0:7447]\n  zenoh: {transport/auth/usrpwd/dictionary_file: users.txt}\n",
    "  listen: [tcp/0.0.0.0:7447]\n  allow_unauthenticated_listen: true\n",
    "  mode: client\n  listen: []\n  connect: [tls/router.plant-a:7447]\n",
])
def test_a_protected_or_declared_listener_loads(tmp_path, zenoh_yaml):
    assert load_station_config(_config(tmp_path, zenoh_yaml)).zenoh.security_problems() == []


@pytest.mark.parametrize("zenoh_yaml, line", [
    ("  listen:\n    - tcp/127.0.0.1:7447\n    - tcp/0.0.0.0:7447\n", 6),                        # plain TCP
    ("  listen: [tls/0.0.0.0:7447]\n" + MTLS.replace("true}", "false}"), 4),                     # TLS, no client certs
    ("  listen: [tcp/0.0.0.0:7447]\n" + MTLS, 4),                                                # mTLS keys, tcp endpoint
    ("  listen: ['tcp/[::]:7447']\n  zenoh: {access_control: {enabled: true, default_permission: allow}}\n", 4),
])
def test_an_open_listener_is_refused_naming_file_line_and_what_is_allowed(tmp_path, zenoh_yaml, line):
    cfg = _config(tmp_path, zenoh_yaml)
    with pytest.raises(ConfigError) as err:
        load_station_config(cfg)
    msg = str(err.value)
    assert f"station.yaml:{line}" in msg and "zenoh.listen" in msg
    assert "reachable from other hosts without authentication" in msg and "allow_unauthenticated_listen" in msg
    if line != 6:
        return  # the command's exit status once (a process start costs seconds)
    out = subprocess.run([sys.executable, "-m", "acquire", "station", "--config", str(cfg)], capture_output=True,
                         text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    assert out.returncode == 2 and "without authentication" in out.stderr


def test_a_station_built_in_code_refuses_an_open_listener_before_opening_a_session(tmp_path):
    cfg = StationConfig(archive=tmp_path / "a", token_file=tmp_path / "t",
                        zenoh={"listen": [f"tcp/0.0.0.0:{free_port()}"]})
    st = Station(cfg, token=TOKEN)
    with pytest.raises(BusConfigError, match="without authentication"):
        st.open()
    assert st.bus is None


def test_nested_and_slashed_zenoh_paths_mean_the_same():
    assert flat_paths({"transport/link/tls": {"enable_mtls": True}, "access_control": {"enabled": True}}) == \
        flat_paths({"transport": {"link": {"tls": {"enable_mtls": True}}}, "access_control/enabled": True}) == \
        {"transport/link/tls/enable_mtls": True, "access_control/enabled": True}


@pytest.mark.timeout(120)
def test_zenoh_user_password_auth_keeps_a_session_without_credentials_off_the_station(tmp_path):
    """The station on a non-loopback endpoint with Zenoh's usrpwd: a client without the
    credentials cannot open a session to it; with them it can (Zenoh enforces it, not us)."""
    import zenoh

    users = tmp_path / "users.txt"
    users.write_text("cell7:cell7-password-Qx81\n")
    users.chmod(0o600)
    port = free_port()
    cfg = StationConfig(archive=tmp_path / "a", token_file=tmp_path / "t", zenoh={
        "mode": "router", "listen": [f"tcp/0.0.0.0:{port}"], "connect": [],
        "zenoh": {"transport/auth/usrpwd": {"user": "station", "password": "station-password-Zt55",
                                            "dictionary_file": str(users)}}})

    def client(user: str | None, password: str | None, timeout_ms: int = 1000):
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        c.insert_json5("connect/timeout_ms", str(timeout_ms))
        c.insert_json5("scouting/multicast/enabled", "false")
        if user:
            c.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
        return zenoh.open(c)

    with Station(cfg, token=TOKEN) as st:
        assert st.bus is not None
        for user, password in ((None, None), ("cell7", "wrong-password-00000")):
            with pytest.raises(zenoh.ZError):
                client(user, password).close()
        session = client("cell7", "cell7-password-Qx81", timeout_ms=20000)
        try:
            assert session.info.routers_zid()  # joined the station's router
        finally:
            session.close()
