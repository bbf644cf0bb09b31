"""Bus viewers (bridge.bus_credentials): a holder of the lab's credentials who may watch, not act.

Credentials keep strangers off the bus, but every holder could command the robot. A user named
``viewer`` or ``viewer-<name>`` receives everything and what it publishes reaches no one: every
process whose file lists it drops its samples, queries and liveliness tokens at the link (Zenoh's
access control). Real Zenoh sessions and real ``xneck`` processes on 127.0.0.1, a real uvicorn
console; every process is stopped within bounded time.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import httpx
import msgspec
import pytest
from server_harness import TOKEN, running_server, wait_until
from test_bus_credentials import ENV, LINK_S, PY, _Collector, _links, twin_stack

from bridge import bus
from bridge.bus_credentials import (
    ENV_CREDENTIALS,
    ENV_USER,
    CredentialsError,
    add_entry,
    export_entry,
    is_viewer,
    load,
    remove_entry,
    viewer_access_control,
    write_new,
)
from bridge.session import free_tcp_port, open_session, publisher, zenoh_config


def _lab(tmp_path: Path, *viewers: str) -> Path:
    """A lab file: operator ``op`` first (presented by default), then ``viewers``."""
    path = write_new(tmp_path / "lab", "op").path
    for v in viewers:
        add_entry(path, v)
    return path


def test_viewers_are_named_viewer_or_viewer_then_a_separator() -> None:
    assert [u for u in ("viewer", "viewer-alice", "viewer_2", "viewer.lab", "viewers", "viewerx", "op",
                        "reviewer", "Viewer-a") if is_viewer(u)] == ["viewer", "viewer-alice", "viewer_2", "viewer.lab"]


def test_a_lab_file_with_viewers_turns_on_the_access_control_that_drops_what_they_publish(tmp_path: Path) -> None:
    plain = load(write_new(tmp_path / "plain", "op").path)
    assert (plain.role, plain.viewers, viewer_access_control(plain.viewers)) == ("operator", (), None)
    assert not zenoh_config([], [], credentials=plain).get_json("access_control").count('"enabled":true')
    lab = load(_lab(tmp_path, "viewer-a", "viewer-b"))
    assert (lab.user, lab.role, lab.viewers) == ("op", "operator", ("viewer-a", "viewer-b"))
    assert load(lab.path, "viewer-b").role == "viewer"
    acl = msgspec.json.decode(zenoh_config([], [], credentials=lab).get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "allow"
    assert [s["usernames"] for s in acl["subjects"]] == [["viewer-a", "viewer-b"]]
    (rule,) = acl["rules"]
    assert rule["permission"] == "deny" and rule["flows"] == ["ingress"] and rule["key_exprs"] == ["**"]
    assert {"put", "delete", "query", "reply", "liveliness_token"} <= set(rule["messages"])
    assert "declare_subscriber" not in rule["messages"]


def test_users_are_added_privately_once_and_exported_alone(tmp_path: Path) -> None:
    path = _lab(tmp_path)
    before = load(path, "op").password
    added = add_entry(path, "viewer-a")
    assert added.user == "viewer-a" and added.users == ("op", "viewer-a") and len(added.password) >= 40
    assert load(path, "op").password == before and path.stat().st_mode & 0o777 == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["lab"]  # no temporary file left beside it
    with pytest.raises(CredentialsError, match="already lists 'viewer-a'"):
        add_entry(path, "viewer-a")
    with pytest.raises(CredentialsError, match="is not 1-64 letters"):
        add_entry(path, "viewer a")
    out = export_entry(path, "viewer-a", tmp_path / "viewer")
    assert out.users == ("viewer-a",) and out.password == added.password and out.role == "viewer"
    assert (tmp_path / "viewer").read_text() == f"viewer-a:{added.password}\n"
    assert (tmp_path / "viewer").stat().st_mode & 0o777 == 0o600
    with pytest.raises(FileExistsError):
        export_entry(path, "op", tmp_path / "viewer")
    with pytest.raises(CredentialsError, match="does not list 'nobody'"):
        export_entry(path, "nobody", tmp_path / "other")
    path.chmod(0o644)
    with pytest.raises(CredentialsError, match="chmod 600"):
        add_entry(path, "viewer-b")


def test_a_viewer_receives_everything_and_what_it_publishes_reaches_no_one(tmp_path: Path) -> None:
    """A listener with the lab file; an operator and a viewer (its exported entry alone) connect.
    Both receive the listener's samples; the listener gets the operator's samples and presence,
    none of the viewer's. The viewer cannot present the operator: it lacks the password."""
    lab = _lab(tmp_path, "viewer-a")
    viewer_file = export_entry(lab, "viewer-a", tmp_path / "viewer").path
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    got, alive = _Collector(), _Collector()
    with open_session([ep], [], credentials=load(lab)) as listener:
        listener.declare_subscriber("xneck/test/**", got)
        listener.liveliness().declare_subscriber("xneck/alive/**", alive)
        with open_session([], [ep], credentials=load(lab, "op")) as op, \
                open_session([], [ep], credentials=load(viewer_file)) as viewer:
            assert wait_until(lambda: _links(op) == 1 and _links(viewer) == 1, 10, 0.05)
            received = {"op": _Collector(), "viewer": _Collector()}
            op.declare_subscriber("xneck/test/**", received["op"])
            viewer.declare_subscriber("xneck/test/**", received["viewer"])
            tokens = [op.liveliness().declare_token("xneck/alive/controller/op"),
                      viewer.liveliness().declare_token("xneck/alive/controller/viewer")]
            # the subscriptions have reached the listener once its probe reaches both (a fixed
            # 0.5 s was a guess; the counts below are exact)
            assert wait_until(lambda: (listener.put("xneck/test/probe", b"0"),
                                       all("xneck/test/probe" in c.keys for c in received.values()))[1], 10, 0.05)
            for _ in range(5):
                for name, s in (("op", op), ("viewer", viewer)):
                    s.put(f"xneck/test/{name}", b"1")
                    s.delete(f"xneck/test/{name}")
                listener.put("xneck/test/state", b"2")
                time.sleep(0.1)
            assert wait_until(lambda: received["viewer"].keys.count("xneck/test/state") == 5, 5, 0.05)
            time.sleep(0.5)
            from_peers = [k for k in got.keys if k not in ("xneck/test/state", "xneck/test/probe")]  # its own reach it
            assert from_peers == ["xneck/test/op"] * 10, got.keys
            assert alive.keys == ["xneck/alive/controller/op"], alive.keys
            assert received["op"].keys.count("xneck/test/state") == 5
            for t in tokens:
                t.undeclare()
    with pytest.raises(CredentialsError, match="'op' is not listed"):
        load(viewer_file, "op")


def test_a_removed_user_gets_no_link_once_the_listener_reads_the_new_file(tmp_path: Path) -> None:
    """Revocation (a lost laptop): ``remove_entry`` then a restart of the listener with the file;
    the removed viewer's own file no longer opens a session, the operator's still does."""
    lab = _lab(tmp_path, "viewer-a")
    viewer_file = export_entry(lab, "viewer-a", tmp_path / "viewer")
    before = lab.read_text()
    left = remove_entry(lab, "viewer-a")
    assert left.users == ("op",) and left.user == "op" and lab.stat().st_mode & 0o777 == 0o600
    assert before.splitlines()[0] == lab.read_text().strip()  # the operator's password is kept
    with pytest.raises(CredentialsError, match="does not list 'viewer-a'"):
        remove_entry(lab, "viewer-a")
    with pytest.raises(CredentialsError, match="last entry"):
        remove_entry(lab, "op")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session([ep], [], credentials=load(lab)), \
            open_session([], [ep], credentials=viewer_file) as viewer, \
            open_session([], [ep], credentials=load(lab)) as op:
        assert wait_until(lambda: _links(op) == 1, 10, 0.05)
        time.sleep(LINK_S)
        assert (_links(op), _links(viewer)) == (1, 0)


@pytest.mark.e2e
def test_a_viewer_watches_the_robot_and_its_estop_and_commands_change_nothing(tmp_path: Path) -> None:
    """A twin bridge and a controller with a lab file that lists a viewer: the viewer (its entry
    alone) receives the states; its e-stops, its force commands (echoing the bridge's epoch, posing
    as the owner) and its liveliness token claiming a controller change nothing; the operator's
    e-stop engages, so the viewer's were dropped, not refused for another reason."""
    lab = _lab(tmp_path, "viewer-a")
    viewer_file = export_entry(lab, "viewer-a", tmp_path / "viewer")
    with twin_stack(tmp_path, ENV | {ENV_CREDENTIALS: str(lab)}, "view-br") as (ep, bridge_log):
        assert "drops what its viewers publish (viewer-a)" in bridge_log.read_text()

        seen: dict[str, list[bus.MotorState]] = {"viewer": [], "op": []}

        def on_state(who: str):
            def cb(sample) -> None:
                seen[who].append(bus.decode(bus.MotorState, sample.payload.to_bytes()))
            return cb

        with open_session([], [ep], credentials=viewer_file) as viewer, open_session([], [ep], credentials=load(lab)) as op:
            viewer.declare_subscriber(bus.MOTOR_STATE, on_state("viewer"))
            op.declare_subscriber(bus.MOTOR_STATE, on_state("op"))
            assert wait_until(lambda: seen["viewer"] and seen["op"], 10, 0.05)
            first = seen["viewer"][-1]
            token = viewer.liveliness().declare_token(bus.liveliness_key("controller", "viewer-ctl"))
            engage = bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="viewer")
            command = publisher(viewer, bus.MOTOR_COMMAND)
            for i in range(10):
                publisher(viewer, bus.ESTOP).put(msgspec.structs.replace(engage, seq=1 + i))
                last = seen["viewer"][-1]
                command.put(bus.ForceCommand(seq=1000 + i, stamp_s=last.stamp_s, force_N=[0.0] * len(last.force_applied_N),
                                             source="viewer", sender="viewer-ctl", epoch=last.epoch))
                time.sleep(0.2)
            state = seen["viewer"][-1]
            assert state.seq > first.seq + 500, (first.seq, state.seq)  # it kept receiving, at 500 Hz
            assert state.drive == "active" and not state.estop_engaged and state.owner != "viewer-ctl", state
            assert all(not s.estop_engaged for s in seen["op"]), "a viewer's e-stop reached the bridge"
            token.undeclare()
            publisher(op, bus.ESTOP).put(msgspec.structs.replace(engage, seq=100, reason="operator"))
            assert wait_until(lambda: seen["op"][-1].estop_engaged, 5, 0.02), seen["op"][-1]
            assert seen["op"][-1].estop_reason == "operator"
        assert "viewer-ctl" not in bridge_log.read_text()


def test_xneck_bus_adds_and_exports_users_and_a_viewer_cannot_start_what_acts(tmp_path: Path) -> None:
    lab = write_new(tmp_path / "lab", "op").path

    def xneck(*argv: str, env: dict[str, str] = ENV) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*PY, *argv], capture_output=True, text=True, env=env, timeout=120,
                              stdin=subprocess.DEVNULL)

    r = xneck("bus", "add-user", str(lab), "viewer-alice")
    assert r.returncode == 0 and "added 'viewer-alice' (viewer)" in r.stdout and "export-user" in r.stdout, r.stderr
    r = xneck("bus", "add-user", str(lab), "viewer-alice")
    assert r.returncode == 2 and "already lists 'viewer-alice'" in r.stderr, r.stderr
    # Audit of 2026-11-29: the file came from the command line, not from XNECK_ZENOH_CREDENTIALS.
    assert f"credentials file {lab} already lists" in r.stderr and ENV_CREDENTIALS not in r.stderr, r.stderr
    r = xneck("bus", "add-user", str(tmp_path / "missing"), "viewer-x")
    assert r.returncode == 2 and f"credentials file {tmp_path / 'missing'}" in r.stderr, r.stderr
    assert ENV_CREDENTIALS not in r.stderr, r.stderr
    out = tmp_path / "alice"
    r = xneck("bus", "export-user", str(lab), "viewer-alice", str(out))
    assert r.returncode == 0 and f"{ENV_CREDENTIALS}={out}" in r.stdout, r.stdout + r.stderr
    assert load(out).users == ("viewer-alice",)
    r = xneck("bus", "export-user", str(lab), "viewer-alice", str(out))
    assert r.returncode == 2 and "never replaced" in r.stderr, r.stderr
    assert xneck("bus", "add-user", str(lab), "viewer-bob").returncode == 0
    r = xneck("bus", "remove-user", str(lab), "viewer-bob")
    assert r.returncode == 0 and "removed 'viewer-bob'" in r.stdout and "users: op, viewer-alice" in r.stdout, r.stderr
    r = xneck("bus", "remove-user", str(lab), "viewer-bob")
    assert r.returncode == 2 and "does not list 'viewer-bob'" in r.stderr, r.stderr
    assert f"credentials file {lab} does not list" in r.stderr and ENV_CREDENTIALS not in r.stderr, r.stderr
    r = xneck("bus", "export-user", str(lab), "viewer-bob", str(tmp_path / "bob"))
    assert r.returncode == 2 and f"credentials file {lab} does not list" in r.stderr, r.stderr
    assert ENV_CREDENTIALS not in r.stderr, r.stderr
    for env in (ENV | {ENV_CREDENTIALS: str(out)}, ENV | {ENV_CREDENTIALS: str(lab), ENV_USER: "viewer-alice"}):
        for argv in (["up", "--exit-after", "1"], ["bridge", "--driver", "twin"], ["controller"], ["twin"],
                     ["camera", "--source", "twin"], ["campaign", "control"], ["campaign", "identification"]):
            r = xneck(*argv, env=env)
            assert r.returncode == 2 and "is a viewer: it may watch" in r.stderr, (argv, r.stderr)
            assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr


def test_a_viewers_console_shows_the_robot_and_refuses_what_would_act(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    lab = _lab(tmp_path, "viewer-a")
    monkeypatch.setenv(ENV_CREDENTIALS, str(export_entry(lab, "viewer-a", tmp_path / "viewer").path))
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with running_server(tmp_path / "d", viser=False) as (base, _app):
        health = httpx.get(base + "/api/system/health", timeout=30).json()
        assert health["bus"]["role"] == "viewer" and health["bus"]["user"] == "viewer-a", health["bus"]
        for path, body in (("/api/system/estop", {"engaged": True}), ("/api/system/abort", {"reason": "x"}),
                           ("/api/campaigns", {"kind": "control"}), ("/api/jog", {"alpha_deg": [0, 0, 0]}),
                           ("/api/jog/stop", None), ("/api/campaigns/none/stop", None)):
            r = httpx.post(base + path, json=body, headers=auth, timeout=30)
            assert r.status_code == 403 and "is a viewer" in r.json()["detail"], (path, r.status_code, r.text)
        r = httpx.post(base + "/api/system/estop", json={"engaged": True}, timeout=30)
        assert r.status_code == 401, r.text  # the token is still checked first
        assert httpx.get(base + "/api/campaigns", timeout=30).status_code == 200
    monkeypatch.setenv(ENV_CREDENTIALS, str(lab))
    with running_server(tmp_path / "d2", viser=False) as (base, _app):
        assert httpx.get(base + "/api/system/health", timeout=30).json()["bus"]["viewers"] == ["viewer-a"]
        r = httpx.post(base + "/api/system/estop", json={"engaged": False, "reason": "operator"}, headers=auth,
                       timeout=30)
        assert r.status_code == 200, r.text
