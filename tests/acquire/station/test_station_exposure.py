"""The station's Zenoh link (issue 32). It sends its SCRAM messages only to a router it has
authenticated: a Unix socket only the router's account (or root, or its own) can have made, or
TLS with the router's CA — never plain tcp/, where any local process can listen while the router
is down. A listener of its own (or the router's) is a Unix socket the kernel guards, or is
protected by Zenoh itself (mTLS, access control or user-password authentication) or explicitly
declared open; else it does not start."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from acquire.live.bus import BusConfigError
from acquire.station.config import StationConfig, flat_paths, load_station_config
from acquire.station.router import RouterConfig, load_router_config
from acquire.station.service import Station
from calib.io.yamlfile import ConfigError
from daemon_harness import MEMBER_UID, NEIGHBOUR_UID, OPERATORS_GID, as_account, free_port, needs_root
from station_harness import station_config

ROOT = Path(__file__).resolve().parents[3]
TOKEN = "Zk3-pQ9xT2mV7bN4cR8sW1yL6hJ0fG"


def _config(tmp_path: Path, zenoh_yaml: str) -> Path:
    cfg = tmp_path / "station.yaml"
    cfg.write_text(f"archive: archive\ntoken_file: station.token\nzenoh:\n{zenoh_yaml}")
    return cfg


MTLS = ("  zenoh:\n    transport/link/tls: {root_ca_certificate: ca.pem, listen_certificate: s.pem,\n"
        "                         listen_private_key: s.key, enable_mtls: true}\n")


@pytest.mark.parametrize("zenoh_yaml", [
    "  mode: client\n",                  # the router's socket on this host (not up here: checked at open)
    "  mode: router\n  listen: [unixsock-stream//run/remaster-station/zenoh.sock]\n  connect: []\n",
    "  listen: [tls/0.0.0.0:7447]\n" + MTLS,
    "  listen: [tcp/0.0.0.0:7447]\n  zenoh: {access_control: {enabled: true, default_permission: deny}}\n",
    "  listen: [tcp/0.0.0.0:7447]\n  zenoh: {transport/auth/usrpwd/dictionary_file: users.txt}\n",
    "  listen: [tcp/127.0.0.1:7447]\n  allow_unauthenticated_listen: true\n",
    "  mode: client\n  listen: []\n  connect: [tls/router.plant-a:7447]\n"
    "  zenoh: {transport/link/tls/root_ca_certificate: ca.pem}\n",
])
def test_a_protected_or_declared_listener_loads(tmp_path, zenoh_yaml):
    assert load_station_config(_config(tmp_path, zenoh_yaml)).zenoh.security_problems() == []


@pytest.mark.parametrize("zenoh_yaml, line, who", [
    ("  listen:\n    - unixsock-stream//run/s.sock\n    - tcp/0.0.0.0:7447\n", 6, "other hosts"),  # plain TCP
    ("  listen: [tcp/127.0.0.1:7447]\n", 4, "any account on this host"),                       # loopback TCP
    ("  listen: [tls/0.0.0.0:7447]\n" + MTLS.replace("true}", "false}"), 4, "other hosts"),    # TLS, no client certs
    ("  listen: [tcp/0.0.0.0:7447]\n" + MTLS, 4, "other hosts"),                               # mTLS keys, tcp endpoint
    ("  listen: ['tcp/[::]:7447']\n  zenoh: {access_control: {enabled: true, default_permission: allow}}\n", 4,
     "other hosts"),
])
def test_an_open_listener_is_refused_naming_file_line_and_what_is_allowed(tmp_path, zenoh_yaml, line, who):
    cfg = _config(tmp_path, zenoh_yaml)
    with pytest.raises(ConfigError) as err:
        load_station_config(cfg)
    msg = str(err.value)
    assert f"station.yaml:{line}" in msg and "zenoh.listen" in msg
    assert f"reachable from {who} without authentication" in msg and "allow_unauthenticated_listen" in msg
    if line != 6:
        return  # the command's exit status once (a process start costs seconds)
    out = subprocess.run([sys.executable, "-m", "acquire", "station", "--config", str(cfg)], capture_output=True,
                         text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    assert out.returncode == 2 and "without authentication" in out.stderr


@pytest.mark.parametrize("endpoint, why", [
    ("tcp/127.0.0.1:7447", "nothing authenticates a tcp/ listener: while the router is down any local process can "
                           "listen there. On the router's host set zenoh.connect to "
                           "[unixsock-stream//run/remaster-router/zenoh.sock]"),
    ("tcp/localhost:7447", "nothing authenticates a tcp/ listener"),
    ("ws/127.0.0.1:8000", "nothing authenticates a ws/ listener"),
    ("tls/router.plant-a:7447", "give zenoh.zenoh transport/link/tls/root_ca_certificate (the CA that signed the "
                                "router's certificate)"),
    ("unixsock-stream/run/zenoh.sock", "the socket must be an absolute path"),
])
def test_a_connect_endpoint_that_authenticates_no_router_is_refused_naming_file_line_and_what_to_set(
        tmp_path, endpoint, why):
    cfg = _config(tmp_path, f"  mode: client\n  connect:\n    - {endpoint}\n")
    with pytest.raises(ConfigError) as err:
        load_station_config(cfg)
    assert f"station.yaml:6:7: zenoh.connect.0: the station sends no credentials to {endpoint!r}: {why}" in str(err.value)


def _bind(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    return s


def test_a_socket_in_a_folder_others_may_write_is_refused_when_loaded_and_when_opened(tmp_path, socket_dir):
    from test_control_local import Impostor   # a local process answering as anyone, keeping what it gets

    folder = socket_dir / "w"
    folder.mkdir()
    folder.chmod(0o777)  # any account could have put the socket here
    endpoint = f"unixsock-stream/{folder / 'zenoh.sock'}"
    cfg = _config(tmp_path, f"  mode: client\n  connect: ['{endpoint}']\n")
    assert load_station_config(cfg).zenoh.connect == [endpoint]      # no socket yet: the router may be starting
    st = Station(StationConfig(archive=tmp_path / "a", token_file=tmp_path / "t",
                               zenoh={"mode": "client", "connect": [endpoint]}), token=TOKEN)
    with pytest.raises(BusConfigError, match=r"no socket at .*zenoh.sock: is the router running"):
        st.open()
    impostor = Impostor(endpoint)
    try:
        with pytest.raises(ConfigError, match=rf"station.yaml:5:\d+: zenoh.connect.0: .*{folder} \(on the way to "
                                              r".*\) has mode 0777: other accounts may write it"):
            load_station_config(cfg)
        with pytest.raises(BusConfigError, match="has mode 0777"):
            st.open()
        assert st.bus is None and impostor.queries() == []   # no session, no liveliness query, no client-first
    finally:
        impostor.close()


@needs_root
def test_a_socket_of_another_account_is_refused_unless_it_is_the_routers(tmp_path, socket_dir):
    path = socket_dir / "zenoh.sock"
    s = _bind(path)
    try:
        os.chown(path, NEIGHBOUR_UID, NEIGHBOUR_UID)
        cfg = _config(tmp_path, f"  mode: client\n  connect: ['unixsock-stream/{path}']\n")
        with pytest.raises(ConfigError, match=rf"zenoh.connect.0: .*the socket {path} belongs to uid {NEIGHBOUR_UID} "
                                              r".*not to the router's account .*set zenoh.router_user"):
            load_station_config(cfg)
        cfg.write_text(cfg.read_text() + f"  router_user: '{NEIGHBOUR_UID}'\n")   # the router runs as that account
        assert load_station_config(cfg).zenoh.connect_problems(socket_up=True) == []
    finally:
        s.close()


@needs_root
def test_only_the_socket_group_reaches_a_station_listening_on_a_unix_socket(tmp_path, socket_dir):
    """The kernel keeps an account without ``socket_group`` off the station's router: it cannot
    connect, so it receives none of the station's queries (no SCRAM client-first or -final)."""
    endpoint = f"unixsock-stream/{socket_dir / 'zenoh.sock'}"
    cfg = station_config(tmp_path, zenoh={"mode": "router", "listen": [endpoint], "connect": [],
                                          "socket_group": str(OPERATORS_GID)})

    def connect() -> dict:
        c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            c.connect(str(socket_dir / "zenoh.sock"))
            return {"connected": True}
        except OSError as exc:
            return {"connected": False, "errno": exc.errno}
        finally:
            c.close()

    with Station(cfg, token=TOKEN):
        st = os.stat(socket_dir / "zenoh.sock")
        assert (st.st_mode & 0o777, st.st_gid) == (0o660, OPERATORS_GID)
        assert as_account(NEIGHBOUR_UID, [], connect) == {"connected": False, "errno": 13}   # EACCES
        assert as_account(MEMBER_UID, [OPERATORS_GID], connect) == {"connected": True}


def test_the_router_listens_on_its_unix_socket_by_default_and_refuses_loopback_tcp(tmp_path):
    assert RouterConfig().listen == ["unixsock-stream//run/remaster-router/zenoh.sock"]
    (tmp_path / "router.yaml").write_text("socket_group: remaster-router-clients\nlisten: [tcp/127.0.0.1:7447]\n")
    with pytest.raises(ConfigError, match=r"router.yaml:2:\d+: listen.0: endpoint 'tcp/127.0.0.1:7447' is reachable "
                                          "from any account on this host without authentication"):
        load_router_config(tmp_path / "router.yaml")
    cfg = load_router_config(ROOT / "systemd" / "router.yaml.example")
    assert cfg.listen == ["unixsock-stream//run/remaster-router/zenoh.sock"]
    assert cfg.socket_group == "remaster-router-clients"


def test_a_listeners_folder_others_may_write_is_refused_before_the_session_opens(tmp_path, socket_dir):
    (socket_dir / "w").mkdir()
    (socket_dir / "w").chmod(0o777)
    st = Station(station_config(tmp_path, zenoh={"mode": "router", "connect": [],
                                                 "listen": [f"unixsock-stream/{socket_dir / 'w' / 'z.sock'}"]}),
                 token=TOKEN)
    with pytest.raises(BusConfigError, match="is writable by others: anyone could replace the socket"):
        st.open()
    assert st.bus is None and not (socket_dir / "w" / "z.sock").exists()


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
