"""Bus credentials (bridge.bus_credentials): a stranger on the network gets no link to the bridge.

The bridge listens on the lab network (docs/bridge.md, deployment). Without credentials any Zenoh
peer there links to it, receives its states and may publish e-stops and commands. With
``XNECK_ZENOH_CREDENTIALS``, processes link only with holders of the file. Real Zenoh sessions
and real ``xneck`` processes on 127.0.0.1; every process is stopped within bounded time.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import msgspec
import pytest
from server_harness import running_server, stop_process_groups, wait_until

from bridge import bus, session
from bridge.bus_credentials import (
    ENV_CREDENTIALS,
    ENV_USER,
    CredentialsError,
    from_env,
    load,
    remove_entry,
    write_new,
)
from bridge.session import access_summary, free_tcp_port, open_session, publisher, zenoh_config

PY = [sys.executable, "-m", "server.cli"]
ENV = {k: v for k, v in os.environ.items() if k not in (ENV_CREDENTIALS, ENV_USER)} | {"PYTHONUNBUFFERED": "1"}
LINK_S = 3.0  # a refused peer retries about every second: three chances to link wrongly


def _file(tmp_path: Path, text: str, mode: int = 0o600, name: str = "creds") -> Path:
    p = tmp_path / name
    p.write_text(text)
    p.chmod(mode)
    return p


GOOD = "ctl:" + "a" * 20 + "\nbridge:" + "b" * 20 + "\n"


@pytest.mark.parametrize(("text", "mode", "says"), [
    (GOOD, 0o644, "chmod 600"),
    (GOOD, 0o620, "chmod 600"),
    ("# lab\n" + GOOD, 0o600, "line 1: not of the form user:password"),
    ("ctl:short\n", 0o600, "16-256 printable"),
    ("ctl:" + "a" * 15 + " b\n", 0o600, "16-256 printable"),
    ("bad user:" + "a" * 20 + "\n", 0o600, "is not 1-64 letters"),
    (GOOD + "ctl:" + "c" * 20 + "\n", 0o600, "line 3: user 'ctl' listed twice"),
    ("\n\n", 0o600, "lists no user:password"),
])
def test_a_credentials_file_that_cannot_be_used_is_refused_with_the_reason(tmp_path: Path, text: str, mode: int,
                                                                           says: str) -> None:
    with pytest.raises(CredentialsError, match=says):
        load(_file(tmp_path, text, mode))


def test_missing_files_unknown_users_and_oversized_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(CredentialsError, match="No such file"):
        load(tmp_path / "none")
    with pytest.raises(CredentialsError, match="not a regular file"):
        load(tmp_path)
    with pytest.raises(CredentialsError, match=r"XNECK_ZENOH_USER='other' is not listed .*users: ctl, bridge"):
        load(_file(tmp_path, GOOD), "other")
    with pytest.raises(CredentialsError, match="more than 65536"):
        load(_file(tmp_path, GOOD + "x" * 70_000, name="big"))


def test_the_first_entry_is_presented_unless_a_user_is_named_and_the_password_never_shows(tmp_path: Path) -> None:
    path = _file(tmp_path, "\n" + GOOD)
    first, named = load(path), load(path, "bridge")
    assert (first.user, first.password, first.users) == ("ctl", "a" * 20, ("ctl", "bridge"))
    assert (named.user, named.password) == ("bridge", "b" * 20)
    assert "a" * 20 not in repr(first) and "a" * 20 not in str(first)
    assert from_env({}) is None and from_env({ENV_CREDENTIALS: " "}) is None
    assert from_env({ENV_CREDENTIALS: str(path), ENV_USER: "bridge"}) == named


def test_new_credentials_are_private_random_and_never_replace_a_file(tmp_path: Path) -> None:
    a, b = write_new(tmp_path / "a"), write_new(tmp_path / "b", "lab-3")
    assert (a.path.stat().st_mode & 0o777, b.user) == (0o600, "lab-3")
    assert a.password != b.password and len(a.password) >= 40
    before = a.path.read_text()
    with pytest.raises(FileExistsError):
        write_new(a.path)
    assert a.path.read_text() == before


def test_zenoh_config_presents_the_credentials_from_the_environment_or_as_given(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    path = _file(tmp_path, GOOD)
    monkeypatch.setenv(ENV_CREDENTIALS, str(path))

    def usrpwd(conf) -> dict:
        return msgspec.json.decode(conf.get_json("transport/auth/usrpwd"))

    assert usrpwd(zenoh_config([], []))["user"] == "ctl"
    assert usrpwd(zenoh_config([], [], credentials=load(path, "bridge")))["user"] == "bridge"
    assert usrpwd(zenoh_config([], [], credentials=None))["user"] is None
    assert usrpwd(zenoh_config([], []))["dictionary_file"] == str(path)
    assert msgspec.json.decode(zenoh_config([], []).get_json("transport/unicast/max_sessions")) == session.MAX_SESSIONS
    path.chmod(0o644)
    with pytest.raises(CredentialsError, match="chmod 600"):
        zenoh_config([], [])
    with pytest.raises(ValueError, match="credentials 'yes'"):
        zenoh_config([], [], credentials="yes")


def test_listening_where_other_machines_reach_it_without_credentials_is_warned(tmp_path: Path,
                                                                               caplog: pytest.LogCaptureFixture) -> None:
    """The configuration is only built, never opened: tests bind 127.0.0.1 only."""
    assert session.exposed_endpoints(["tcp/127.0.0.1:7447", "tcp/localhost:1", "tcp/[::1]:2", "unixsock-stream//tmp/s",
                                      "tcp/0.0.0.0:7447", "tcp/192.168.1.5:7447", "tcp/[::]:7447"]) == \
        ["tcp/0.0.0.0:7447", "tcp/192.168.1.5:7447", "tcp/[::]:7447"]
    with caplog.at_level(logging.INFO, logger="bridge.session"):
        session._log_access(zenoh_config(["tcp/0.0.0.0:17447"], [], credentials=None))
        session._log_access(zenoh_config(["tcp/127.0.0.1:17447"], [], credentials=None))
        session._log_access(zenoh_config(["tcp/0.0.0.0:17448"], [], credentials=load(_file(tmp_path, GOOD))))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "tcp/0.0.0.0:17447 without credentials" in warnings[0], warnings
    assert any("links only with holders of" in r.getMessage() for r in caplog.records if r.levelno == logging.INFO)


class _Collector:
    def __init__(self) -> None:
        self.keys: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        with self.lock:
            self.keys.append(str(sample.key_expr))


def _links(s) -> int:
    return len(list(s.info.peers_zid()))


def test_only_holders_of_the_file_link_in_either_direction(tmp_path: Path) -> None:
    """A listener with credentials; peers with the same file link (any entry, both directions), a peer
    without credentials, one with another lab's file, and a listener without credentials get no link."""
    ours, theirs = _file(tmp_path, GOOD), write_new(tmp_path / "theirs", "ctl").path
    ep, plain_ep = f"tcp/127.0.0.1:{free_tcp_port()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    got, got_plain = _Collector(), _Collector()
    with open_session([ep], [], credentials=load(ours, "bridge")) as listener, \
            open_session([plain_ep], [], credentials=None) as plain_listener:
        listener.declare_subscriber("xneck/test/**", got)
        plain_listener.declare_subscriber("xneck/test/**", got_plain)
        peers = {"ctl": ([ep], load(ours)), "none": ([ep], None), "theirs": ([ep], load(theirs)),
                 "to-plain": ([plain_ep], load(ours))}
        opened = {name: open_session([], connect, credentials=c) for name, (connect, c) in peers.items()}
        try:
            assert wait_until(lambda: _links(opened["ctl"]) == 1, 10, 0.05)
            time.sleep(LINK_S)
            assert {name: _links(s) for name, s in opened.items()} == {"ctl": 1, "none": 0, "theirs": 0, "to-plain": 0}
            for name, s in opened.items():
                s.put(f"xneck/test/{name}", b"1")
            assert wait_until(lambda: "xneck/test/ctl" in got.keys, 5, 0.05)
            time.sleep(0.5)
            assert got.keys == ["xneck/test/ctl"] and got_plain.keys == []
        finally:
            for s in opened.values():
                s.close()


def test_a_process_accepts_at_most_max_sessions(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each session of a subscriber costs the bridge a send per state: the number is bounded."""
    monkeypatch.setattr(session, "MAX_SESSIONS", 3)
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session([ep], [], credentials=None) as listener:
        monkeypatch.setattr(session, "MAX_SESSIONS", 64)
        peers = [open_session([], [ep], credentials=None) for _ in range(5)]
        try:
            time.sleep(LINK_S)
            assert _links(listener) == 3 and sorted(_links(p) for p in peers) == [0, 0, 1, 1, 1]
        finally:
            for p in peers:
                p.close()


@contextlib.contextmanager
def twin_stack(tmp_path: Path, env: dict[str, str], instance: str, scheme: str = "tcp") -> Iterator[tuple[str, Path]]:
    """A twin bridge listening on a loopback port (``scheme``: tcp or tls) and a law-2 controller
    connected to it, both with ``env`` (its credentials, its TLS folder); yields (the bridge's
    endpoint, its log) once the controller drives it, and stops both."""
    ep = f"{scheme}/127.0.0.1:{free_tcp_port()}"
    procs = []
    try:
        for name, argv in (("bridge", ["bridge", "--driver", "twin", "--listen", ep, "--instance", instance]),
                           ("controller", ["controller", "--law", "2", "--connect", ep])):
            with open(tmp_path / f"{name}.log", "wb") as log:
                procs.append(subprocess.Popen([*PY, *argv], stdout=log, stderr=subprocess.STDOUT,
                                              stdin=subprocess.DEVNULL, env=env, start_new_session=True))
        bridge_log = tmp_path / "bridge.log"
        assert wait_until(lambda: "bumpless ramp done" in bridge_log.read_text(errors="replace"), 120, 0.3), \
            bridge_log.read_text(errors="replace") + (tmp_path / "controller.log").read_text(errors="replace")
        yield ep, bridge_log
    finally:
        stop_process_groups(procs)


@pytest.mark.e2e
def test_a_bridge_with_credentials_ignores_a_stranger_and_obeys_its_controller(tmp_path: Path) -> None:
    """A twin bridge and a controller with credentials, the bridge listening: the controller drives
    it; a stranger's session gets no state and its e-stop changes nothing; the same e-stop from a
    holder of the file engages (so the stranger's was refused, not ignored for another reason)."""
    creds = write_new(tmp_path / "creds")
    with twin_stack(tmp_path, ENV | {ENV_CREDENTIALS: str(creds.path)}, "cred-br") as (ep, bridge_log):
        assert "links only with holders of" in bridge_log.read_text()

        latest: dict[str, bus.MotorState] = {}
        seen: list[bus.MotorState] = []

        def on_state(sample) -> None:
            latest["state"] = bus.decode(bus.MotorState, sample.payload.to_bytes())
            seen.append(latest["state"])

        stranger_states = _Collector()
        engage = bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="stranger")
        with open_session([], [ep], credentials=None) as stranger, open_session([], [ep], credentials=creds) as lab:
            stranger.declare_subscriber(bus.MOTOR_STATE, stranger_states)
            lab.declare_subscriber(bus.MOTOR_STATE, on_state)
            assert wait_until(lambda: "state" in latest, 10, 0.05)
            for _ in range(10):
                publisher(stranger, bus.ESTOP).put(engage)
                time.sleep(0.2)
            assert (_links(stranger), stranger_states.keys) == (0, [])
            # Never latched nor disabled by the stranger; a hold of a loaded machine's late answer
            # may come and go (CI of session 42: one state said 'hold').
            assert not [m for m in seen if m.estop_engaged or m.drive == "disabled"], seen[-1]
            assert any(m.drive == "active" for m in seen[-50:]), seen[-1]
            publisher(lab, bus.ESTOP).put(msgspec.structs.replace(engage, reason="lab"))
            assert wait_until(lambda: latest["state"].estop_engaged, 5, 0.02), latest["state"]
            assert latest["state"].estop_reason == "lab"


def test_xneck_bus_credentials_writes_a_private_file_once_and_stacks_refuse_a_loose_one(tmp_path: Path) -> None:
    path = tmp_path / "bus-credentials"
    r = subprocess.run([*PY, "bus", "credentials", str(path), "--user", "lab"], capture_output=True, text=True,
                       env=ENV, timeout=60, stdin=subprocess.DEVNULL)
    assert r.returncode == 0 and f"{ENV_CREDENTIALS}={path}" in r.stdout, r.stdout + r.stderr
    assert path.stat().st_mode & 0o777 == 0o600 and load(path).user == "lab"
    before = path.read_text()
    r = subprocess.run([*PY, "bus", "credentials", str(path)], capture_output=True, text=True, env=ENV, timeout=60,
                       stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and "never replaced" in r.stderr and path.read_text() == before, r.stderr
    path.chmod(0o640)
    for argv in (["up", "--exit-after", "1"], ["server"], ["bridge", "--driver", "twin"], ["controller"], ["twin"],
                 ["camera", "--source", "twin"], ["campaign", "control"], ["campaign", "identification"]):
        r = subprocess.run([*PY, *argv], capture_output=True, text=True, env=ENV | {ENV_CREDENTIALS: str(path)},
                           timeout=120, stdin=subprocess.DEVNULL)
        assert r.returncode == 2 and "chmod 600" in r.stderr and "Traceback" not in r.stderr, (argv, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_flood_of_strangers_gets_no_session_with_credentials_and_a_bounded_number_without(tmp_path: Path) -> None:
    """The benchmark's machinery (benchmarks/bus_flood.py) on a small flood: the rogue's sessions,
    its own process without credentials, link to the publisher only when it has none."""
    from test_bus_dead_peers import bus_peer

    run_flood = bus_peer.run_flood
    creds = write_new(tmp_path / "c")
    # Both floods at once, each its own publisher, control peer and rogue on ports of its own (as
    # test_bus_dead_peers runs its two scenarios): each is mostly its 6 s of states.
    with ThreadPoolExecutor(2) as pool:
        with_creds_run = pool.submit(run_flood, "sessions", 4, 6.0, ENV | {ENV_CREDENTIALS: str(creds.path)}, ENV)
        without_run = pool.submit(run_flood, "sessions", 4, 6.0, ENV, ENV)
        with_creds, without = with_creds_run.result(timeout=180), without_run.result(timeout=180)
    assert with_creds["rogue"]["opened"] == 4 and with_creds["rogue"]["linked"] == 0, with_creds
    assert without["rogue"]["linked"] == 4, without
    assert with_creds["received"] > 1000 and without["received"] > 1000, json.dumps([with_creds, without])


@pytest.mark.e2e
def test_xneck_up_says_when_its_remote_bridge_refuses_it_or_is_not_there(tmp_path: Path) -> None:
    """The commissioning mistakes that otherwise look alike (a bridge that never appears): the
    board's bridge holds credentials the PC lacks, and no bridge listening at all."""
    creds = write_new(tmp_path / "creds")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"

    def up(at: str) -> str:
        r = subprocess.run([*PY, "up", "--no-bridge", "--bridge-at", at, "--port", str(free_tcp_port()), "--hub",
                            f"tcp/127.0.0.1:{free_tcp_port()}", "--data-dir", str(tmp_path / "d"), "--viser-port",
                            str(free_tcp_port()), "--exit-after", "1"],
                           capture_output=True, text=True, env=ENV, timeout=180, stdin=subprocess.DEVNULL)
        assert r.returncode == 0, r.stdout + r.stderr
        return r.stdout

    assert f"nothing listens at {ep} yet" in up(ep)
    with open(tmp_path / "bridge.log", "wb") as log:
        bridge = subprocess.Popen([*PY, "bridge", "--driver", "twin", "--listen", ep], stdout=log,
                                  stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                  env=ENV | {ENV_CREDENTIALS: str(creds.path)}, start_new_session=True)
    try:
        assert wait_until(lambda: "links only with holders of" in (tmp_path / "bridge.log").read_text(), 60, 0.2)
        out = up(ep)
        assert f"{ep} answers but refuses this machine's bus session: the bus credentials differ" in out, out
        assert f"no {ENV_CREDENTIALS}" in out, out
    finally:
        stop_process_groups([bridge])


def test_who_may_link_is_summarised_for_the_console(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    creds = load(_file(tmp_path, GOOD))
    assert access_summary(["tcp/127.0.0.1:7447"], ["tcp/127.0.0.1:7448"], None)["open"] is False
    assert access_summary(["tcp/0.0.0.0:7447"], [], None) == {
        "credentials": False, "user": None, "role": "operator", "viewers": [], "exposed": ["tcp/0.0.0.0:7447"],
        "remote": [], "open": True, "encrypted": False}
    # A remote bridge linked without credentials has none either: the bridge is open.
    assert access_summary(["tcp/127.0.0.1:0"], ["tcp/10.0.0.7:7447"], None)["open"] is True
    assert access_summary(["tcp/0.0.0.0:7447"], ["tcp/10.0.0.7:7447"], creds) == {
        "credentials": True, "user": "ctl", "role": "operator", "viewers": [], "exposed": ["tcp/0.0.0.0:7447"],
        "remote": ["tcp/10.0.0.7:7447"], "open": False, "encrypted": False}
    monkeypatch.setenv(ENV_CREDENTIALS, str(creds.path))
    with running_server(tmp_path / "d", viser=False) as (base, _app):
        import httpx

        bus_state = httpx.get(base + "/api/system/health", timeout=30).json()["bus"]
        # A user revoked (or added) after the start is not in force until a restart: the console says so.
        time.sleep(0.01)  # a distinct modification time, even on a coarse clock
        remove_entry(creds.path, "bridge")
        changed = httpx.get(base + "/api/system/health", timeout=30).json()["bus"]["changed_since_start"]
    assert bus_state == {"credentials": True, "user": "ctl", "role": "operator", "viewers": [], "exposed": [],
                         "remote": [], "open": False, "encrypted": False, "changed_since_start": []}, bus_state
    assert changed == [str(creds.path)], changed


def test_xneck_bus_creates_the_missing_folder_of_the_files_it_writes(tmp_path: Path) -> None:
    """Audit of 2026-11-29: the docs' first distributed step, ``xneck bus credentials
    ~/.config/xneck/bus-credentials``, failed on a fresh PC with ``~/.config/xneck is not a
    directory`` (it did not exist). A missing folder is created (mode 700); something in the way
    that is not a folder is still refused, by its name."""
    home = tmp_path / "home"
    home.mkdir()

    def xneck(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*PY, *argv], capture_output=True, text=True, env=ENV | {"HOME": str(home)},
                              timeout=60, stdin=subprocess.DEVNULL)

    r = xneck("bus", "credentials", "~/.config/xneck/bus-credentials")
    made = home / ".config" / "xneck" / "bus-credentials"
    assert r.returncode == 0 and f"{ENV_CREDENTIALS}={made}" in r.stdout, r.stdout + r.stderr
    assert made.parent.stat().st_mode & 0o777 == 0o700 and made.stat().st_mode & 0o777 == 0o600
    r = xneck("bus", "export-user", str(made), "xneck", str(tmp_path / "for" / "laptop" / "creds"))
    assert r.returncode == 0 and load(tmp_path / "for" / "laptop" / "creds").users == ("xneck",), r.stderr
    assert (tmp_path / "for" / "laptop").stat().st_mode & 0o777 == 0o700
    (tmp_path / "a-file").write_text("")
    for argv in (["credentials", str(tmp_path / "a-file" / "sub" / "creds")],
                 ["export-user", str(made), "xneck", str(tmp_path / "a-file" / "creds")]):
        r = xneck("bus", *argv)
        assert r.returncode == 2 and f"{tmp_path / 'a-file'} is not a directory" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
