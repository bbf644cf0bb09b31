"""Bus encryption (bridge.bus_tls): tls/ links that hide the traffic and certify both ends.

Credentials keep strangers from opening a session, but the traffic was plain TCP. With
``XNECK_ZENOH_TLS`` (a folder made by ``xneck bus tls``), ``tls/`` endpoints encrypt and both ends
prove a certificate of the lab's authority. Real Zenoh sessions and real ``xneck`` processes on
127.0.0.1; every process is stopped within bounded time.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import zenoh
from server_harness import wait_until
from test_bus_credentials import ENV, LINK_S, PY, _Collector, _links, twin_stack

from bridge import bus, session
from bridge.bus_credentials import ENV_CREDENTIALS
from bridge.bus_credentials import write_new as write_credentials
from bridge.bus_tls import ENV_TLS, TlsError, load, write_new, zenoh_tls
from bridge.session import access_summary, free_tcp_port, open_session, zenoh_config


def test_a_new_folder_holds_a_private_key_and_a_certificate_naming_the_hosts(tmp_path: Path) -> None:
    made = write_new(tmp_path / "tls", ["127.0.0.1", "board.lab", "::1"], days=30)
    assert made.hosts == ("127.0.0.1", "board.lab", "0:0:0:0:0:0:0:1")  # as the standard library spells ::1
    assert 29 < made.days_left() <= 30
    modes = {p.name: p.stat().st_mode & 0o777 for p in made.path.iterdir()}
    assert modes == {"ca.pem": 0o644, "node.pem": 0o644, "node.key": 0o600, "ca.key": 0o600}, modes
    assert made.path.stat().st_mode & 0o777 == 0o700
    with pytest.raises(FileExistsError):
        write_new(tmp_path / "tls", ["127.0.0.1"])
    for hosts, says in (([], "at least one address"), (["a b"], "neither an IP address"), (["tcp/x"], "neither")):
        with pytest.raises(TlsError, match=says):
            write_new(tmp_path / "other", hosts)
    with pytest.raises(TlsError, match="days must be 1-3650"):
        write_new(tmp_path / "other", ["127.0.0.1"], days=0)
    section = zenoh_tls(made)
    assert section["enable_mtls"] is True and section["verify_name_on_connect"] is True
    assert section["listen_private_key"] == section["connect_private_key"] == str(made.path / "node.key")


def test_a_folder_that_cannot_be_used_is_refused_with_the_reason(tmp_path: Path) -> None:
    good = write_new(tmp_path / "good", ["127.0.0.1"], days=10).path
    other = write_new(tmp_path / "other", ["127.0.0.1"]).path
    with pytest.raises(TlsError, match="is not a directory"):
        load(tmp_path / "missing")
    with pytest.raises(TlsError, match="expired on"):
        load(good, now=time.time() + 11 * 86400)
    with pytest.raises(TlsError, match=r"valid only from .* clock"):
        load(good, now=time.time() - 86400)
    cases = {
        "no key": lambda d: (d / "node.key").unlink(),
        "open key": lambda d: (d / "node.key").chmod(0o644),
        "garbage certificate": lambda d: (d / "node.pem").write_text("-----BEGIN CERTIFICATE-----\nnope\n"
                                                                      "-----END CERTIFICATE-----\n"),
        "key for a certificate": lambda d: (d / "ca.pem").write_text((d / "node.key").read_text()),
        "another folder's key": lambda d: (d / "node.key").write_text((other / "node.key").read_text()),
    }
    says = {"no key": "node.key: No such file", "open key": "chmod 600", "garbage certificate": "not a readable X.509",
            "key for a certificate": "ca.pem holds no PEM certificate",
            "another folder's key": "node.key is not the key of node.pem"}
    for name, spoil in cases.items():
        d = tmp_path / name.replace(" ", "-").replace("'", "")
        shutil.copytree(good, d)
        (d / "node.key").chmod(0o600)
        spoil(d)
        with pytest.raises(TlsError, match=says[name]):
            load(d)


def test_a_tls_endpoint_needs_a_folder_and_the_console_says_the_links_are_encrypted(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=f"tls/127.0.0.1:7447 needs {ENV_TLS}"):
        zenoh_config(["tls/127.0.0.1:7447"], [], credentials=None, tls=None)
    made = write_new(tmp_path / "tls", ["127.0.0.1"])
    section = json.loads(zenoh_config(["tls/127.0.0.1:7447"], [], credentials=None, tls=made).get_json("transport/link/tls"))
    assert section["root_ca_certificate"] == str(made.ca) and section["enable_mtls"] is True
    assert access_summary(["tls/0.0.0.0:7447"], [], None, made)["encrypted"] is True
    assert access_summary(["tls/0.0.0.0:7447"], [], None, made)["open"] is False  # only the lab's certificate links
    mixed = access_summary(["tls/0.0.0.0:7447", "tcp/0.0.0.0:7448"], [], None, made)
    assert mixed["encrypted"] is False and mixed["open"] is True
    assert access_summary(["tcp/127.0.0.1:0"], ["tls/10.0.0.7:7447"], None, made)["encrypted"] is True
    assert access_summary(["tcp/127.0.0.1:0"], ["tls/10.0.0.7:7447"], None, None)["encrypted"] is False


def test_processes_say_what_tls_covers_and_warn_of_plain_tcp_and_an_ending_certificate(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The configuration is only built, never opened: tests bind 127.0.0.1 only. Without credentials,
    an exposed tls/ endpoint admits the lab's certificate only (no warning); an exposed tcp/ one
    admits anyone, and is unencrypted although TLS is set (two warnings)."""
    made = write_new(tmp_path / "tls", ["127.0.0.1"], days=10)
    with caplog.at_level(logging.INFO, logger="bridge.session"):
        session._log_access(zenoh_config(["tls/0.0.0.0:17450"], [], credentials=None, tls=made))
        session._log_access(zenoh_config(["tcp/0.0.0.0:17451"], [], credentials=None, tls=made))
    info = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("tls/ links encrypted" in m and "names 127.0.0.1" in m and "10 days left" in m for m in info), info
    assert sum("expires on" in w for w in warnings) == 2, warnings
    others = [w for w in warnings if "expires on" not in w]
    assert len(others) == 2 and all("tcp/0.0.0.0:17451" in w for w in others), warnings
    assert any("unencrypted although" in w for w in others) and any("without credentials" in w for w in others)


def test_only_peers_certified_by_the_lab_for_that_address_link(tmp_path: Path) -> None:
    """A tls listener: a peer with the same folder links and its samples arrive; a peer with
    another lab's folder, a TLS peer without a certificate of its own (mTLS), a plain TCP peer on
    the tls port and a peer reaching the listener by a name its certificate does not hold get no
    link."""
    lab, other = write_new(tmp_path / "lab", ["127.0.0.1"]), write_new(tmp_path / "other", ["127.0.0.1"])
    port = free_tcp_port()
    ep = f"tls/127.0.0.1:{port}"
    got = _Collector()
    with open_session([ep], [], credentials=None, tls=lab) as listener:
        listener.declare_subscriber("xneck/test/**", got)
        conf = zenoh_config([], [], credentials=None, tls=None)
        conf.insert_json5("connect/endpoints", json.dumps([ep]))
        conf.insert_json5("transport/link/tls", json.dumps({"root_ca_certificate": str(lab.ca)}))
        no_client_cert = zenoh.open(conf)
        peers = {"lab": open_session([], [ep], credentials=None, tls=lab),
                 "other lab": open_session([], [ep], credentials=None, tls=other),
                 "plain tcp": open_session([], [f"tcp/127.0.0.1:{port}"], credentials=None, tls=None),
                 "wrong name": open_session([], [f"tls/localhost:{port}"], credentials=None, tls=lab),
                 "no client certificate": no_client_cert}
        try:
            time.sleep(LINK_S)
            assert {n: _links(s) for n, s in peers.items()} == {"lab": 1, "other lab": 0, "plain tcp": 0,
                                                                "wrong name": 0, "no client certificate": 0}
            for name, s in peers.items():
                s.put(f"xneck/test/{name.replace(' ', '-')}", b"1")
            time.sleep(0.5)
            assert got.keys == ["xneck/test/lab"], got.keys
        finally:
            for s in peers.values():
                s.close()


@pytest.mark.e2e
def test_a_bridge_and_its_controller_over_tls_with_credentials(tmp_path: Path) -> None:
    """The deployment's bus: the bridge listens on tls/, the controller connects over it, both
    with credentials; the controller drives the bridge and a holder of both reads its states."""
    lab, creds = write_new(tmp_path / "tls", ["127.0.0.1"]), write_credentials(tmp_path / "creds")
    env = ENV | {ENV_TLS: str(lab.path), ENV_CREDENTIALS: str(creds.path)}
    with twin_stack(tmp_path, env, "tls-br", scheme="tls") as (ep, bridge_log):
        assert ep.startswith("tls/") and "tls/ links encrypted" in bridge_log.read_text()
        states = _Collector()
        with open_session([], [ep], credentials=creds, tls=lab) as s:
            s.declare_subscriber(bus.MOTOR_STATE, states)
            assert wait_until(lambda: len(states.keys) > 100, 10, 0.05)


def test_xneck_bus_tls_writes_a_folder_once_and_every_command_refuses_a_bad_one(tmp_path: Path) -> None:
    path = tmp_path / "bus-tls"

    def xneck(*argv: str, env: dict[str, str] = ENV) -> subprocess.CompletedProcess[str]:
        # A data directory of its own: ./data is shared with whatever else runs from the checkout
        # (a CI run saw `campaign control` refuse ./data/cli-campaigns, ENOENT, before the TLS check).
        return subprocess.run([*PY, *argv], capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL,
                              env={"XNECK_DATA_DIR": str(tmp_path / "data"), **env})

    r = xneck("bus", "tls", str(path), "--host", "127.0.0.1", "--host", "board.lab")
    assert r.returncode == 0 and f"{ENV_TLS}={path}" in r.stdout and "names 127.0.0.1, board.lab" in r.stdout, r.stderr
    assert load(path).hosts == ("127.0.0.1", "board.lab")
    r = xneck("bus", "tls", str(path), "--host", "127.0.0.1")
    assert r.returncode == 2 and "never replaced" in r.stderr, r.stderr
    r = xneck("bridge", "--driver", "twin", "--listen", "tls/127.0.0.1:7447")
    assert r.returncode == 2 and f"needs {ENV_TLS}" in r.stderr and "Traceback" not in r.stderr, r.stderr
    (path / "node.key").chmod(0o644)
    for argv in (["up", "--exit-after", "1"], ["server"], ["bridge", "--driver", "twin"], ["controller"], ["twin"],
                 ["camera", "--source", "twin"], ["campaign", "control"]):
        r = xneck(*argv, env=ENV | {ENV_TLS: str(path)})
        assert r.returncode == 2 and "chmod 600" in r.stderr and "Traceback" not in r.stderr, (argv, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_xneck_bus_check_says_the_settings_and_whether_each_endpoint_links(tmp_path: Path) -> None:
    """The commissioning check, against a real listener with credentials and TLS: linked with the
    same settings; another lab's credentials are refused by the listener, nothing listens at a free
    port; exit status 1 for those, 2 for settings that cannot be used."""
    lab, creds = write_new(tmp_path / "tls", ["127.0.0.1"]), write_credentials(tmp_path / "creds", "op")
    theirs = write_credentials(tmp_path / "theirs", "op")
    env = ENV | {ENV_TLS: str(lab.path), ENV_CREDENTIALS: str(creds.path)}
    ep, free = f"tls/127.0.0.1:{free_tcp_port()}", f"tls/127.0.0.1:{free_tcp_port()}"

    def check(*endpoints: str, env: dict[str, str] = env) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*PY, "bus", "check", *endpoints], capture_output=True, text=True, env=env, timeout=120,
                              stdin=subprocess.DEVNULL)

    with open_session([ep], [], credentials=creds, tls=lab):
        r = check(ep)
        assert r.returncode == 0, r.stdout + r.stderr
        assert f"credentials: {creds.path}, presenting 'op' (operator)" in r.stdout
        assert f"TLS: {lab.path}, certificate names 127.0.0.1" in r.stdout and f"{ep}: linked" in r.stdout, r.stdout
        r = check(ep, free, env=env | {ENV_CREDENTIALS: str(theirs.path)})
        assert r.returncode == 1, r.stdout + r.stderr
        assert f"{ep} answers but refuses this machine's bus session: the bus credentials differ" in r.stdout
        assert f"nothing listens at {free}" in r.stdout, r.stdout
    r = check(env=ENV)
    assert r.returncode == 0 and "credentials: none" in r.stdout and "TLS: none" in r.stdout, r.stdout
    (lab.path / "node.key").chmod(0o644)
    r = check(ep)
    assert r.returncode == 2 and "chmod 600" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_xneck_bus_tls_creates_the_missing_folder_above_its_own(tmp_path: Path) -> None:
    """Audit of 2026-11-29: on a fresh PC ``~/.config/xneck`` does not exist; ``xneck bus tls
    ~/.config/xneck/bus-tls`` creates it (mode 700) as credentials does; a file in the way is named."""
    path = tmp_path / "config" / "xneck" / "bus-tls"
    r = subprocess.run([*PY, "bus", "tls", str(path), "--host", "127.0.0.1"], capture_output=True, text=True,
                       env=ENV, timeout=120, stdin=subprocess.DEVNULL)
    assert r.returncode == 0 and load(path).hosts == ("127.0.0.1",), r.stderr
    assert path.parent.stat().st_mode & 0o777 == 0o700
    (tmp_path / "a-file").write_text("")
    r = subprocess.run([*PY, "bus", "tls", str(tmp_path / "a-file" / "bus-tls"), "--host", "127.0.0.1"],
                       capture_output=True, text=True, env=ENV, timeout=120, stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and f"{tmp_path / 'a-file'} is not a directory" in r.stderr, r.stderr
