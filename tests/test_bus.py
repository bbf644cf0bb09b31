"""The bus contract and the Zenoh helpers, on real Zenoh sessions over TCP loopback."""

from __future__ import annotations

import logging
import os
import re
import threading
from typing import Any

import msgspec
import pytest
import zenoh
from busutil import wait_until

from bridge import bus
from bridge.session import (
    CONNECT_RETRY_MS,
    free_tcp_port,
    liveliness_token,
    open_session,
    publisher,
    subscribe_latest,
    zenoh_config,
    zenoh_runtime_environment,
)


def sample_messages() -> dict[str, bus.BusMessage]:
    """One valid message per fixed key of the registry, plus a health key."""
    common = {"seq": 7, "stamp_s": 12.5}
    return {
        bus.MOTOR_STATE: bus.MotorState(**common, theta_rad=[0.1, -0.2, 0.3, 0.0], force_applied_N=[1.0, 2.0, 3.0, 4.0], drive="active", epoch="e1", bridge="b1"),
        bus.MOTOR_COMMAND: bus.ForceCommand(**common, force_N=[5.0, 6.0, 7.0, 8.0], source="pid", sender="ctl", epoch="e1"),
        bus.CAMERA_ALPHA: bus.CameraAlpha(**common, alpha_ip_rad=[0.01, 0.02], capture_stamp_s=12.4),
        bus.TWIN_TRUTH: bus.Truth(
            **common, alpha_rad=[0.1, 0.2], alpha_dot_rad_s=[0.0, 0.1], theta_rad=[1.0] * 4, theta_dot_rad_s=[0.0] * 4,
            tension_N=[10.0, 0.0, 5.0, 5.0], elongation_m=[1e-4, 0.0, 5e-5, 5e-5], slack=[False, True, False, False],
            near_singular=False,
        ),
        bus.CONTROLLER_STATUS: bus.ControllerStatus(
            **common, law="pid", tick_s=0.002, compute_s=1.5e-4, overruns=0, deadline_misses=1,
            saturated=[False] * 4, alpha_hat_rad=[0.1, 0.2], alpha_d_rad=[0.1, 0.25], e_rad=[0.0, 0.05], holding=False,
        ),
        bus.CAMPAIGN_EVENTS: bus.CampaignEvent(**common, campaign_id="c-1", kind="identification", event="progress", progress=0.5),
        bus.ESTOP: bus.EStop(**common, engaged=True, reason="console button"),
        bus.health_key("bridge", "0"): bus.Health(
            **common, process="bridge", instance="0", uptime_s=3.0, received={bus.MOTOR_COMMAND: 10}, rejected={bus.MOTOR_COMMAND: 2},
        ),
    }


# --- the contract, without a bus ---------------------------------------------------------------


def test_every_message_round_trips_and_has_a_titled_schema() -> None:
    for key, msg in sample_messages().items():
        msg_type = bus.message_type(key)
        assert msg_type is type(msg)
        assert bus.decode(key, bus.encode(msg)) == msg
        schema = bus.json_schema(msg_type)
        assert schema["title"] == msg_type.__name__
        assert schema["properties"]["v"]["const"] == bus.schema_version(msg_type)
        assert "v" in schema["required"] and "$ref" not in msgspec.json.encode(schema).decode()
        assert bus.mcap_topic(key) == "/" + key and bus.key_of_topic(bus.mcap_topic(key)) == key


GOOD_STATE = b'{"v":2,"seq":1,"stamp_s":0.5,"theta_rad":[0.1],"force_applied_N":[1.0],"drive":"active","epoch":"e","bridge":"b"}'


@pytest.mark.parametrize(
    ("payload", "reason_part"),
    [
        (b"{not json", "malformed JSON"),
        (b"", "malformed JSON"),
        (b"[1, 2]", "schema version"),
        (GOOD_STATE.replace(b'"v":2', b'"v":1'), "version 1 is not supported (expected 2)"),
        (GOOD_STATE.replace(b'"v":2,', b""), "missing required field `v`"),
        (GOOD_STATE.replace(b"0.5", b"NaN"), "malformed JSON"),
        (GOOD_STATE.replace(b"0.5", b"Infinity"), "malformed JSON"),
        (GOOD_STATE.replace(b"0.5", b"1e999"), "out of range"),
        (GOOD_STATE.replace(b"[0.1]", b"[null]"), "Expected `float`, got `null`"),
        (GOOD_STATE.replace(b"[0.1]", b'["0.1"]'), "Expected `float`, got `str`"),
        (GOOD_STATE.replace(b'"seq":1', b'"seq":true'), "Expected `int`, got `bool`"),
        (GOOD_STATE.replace(b',"drive":"active"', b""), "missing required field `drive`"),
        (GOOD_STATE.replace(b',"epoch":"e"', b""), "missing required field `epoch`"),
        (GOOD_STATE.replace(b'"active"', b'"flying"'), "Invalid enum value"),
        (GOOD_STATE[:-1] + b',"extra":1}', "unknown field `extra`"),
        (b"\xff\xfe\x00", "malformed JSON"),
    ],
)
def test_decode_rejects_bad_payloads_with_a_reason(payload: bytes, reason_part: str) -> None:
    with pytest.raises(bus.BusDecodeError) as err:
        bus.decode(bus.MotorState, payload)
    assert reason_part in err.value.reason
    assert err.value.reason.startswith("MotorState: ")


def test_decode_never_raises_anything_else() -> None:
    for bad_input in (None, 42, "text", {"v": 1}):
        with pytest.raises(bus.BusDecodeError):
            bus.decode(bus.MotorState, bad_input)  # type: ignore[arg-type]
    with pytest.raises(bus.BusDecodeError, match="no message type"):
        bus.decode("xneck/unknown", GOOD_STATE)
    with pytest.raises(bus.BusDecodeError, match="not a bus message type"):
        bus.decode(dict, GOOD_STATE)  # type: ignore[arg-type]


def test_decode_refuses_payloads_larger_than_their_type_allows() -> None:
    """Audit of 2026-11-26: a 20 MB ForceCommand was parsed in the bridge's callback (134 ms). Every
    type has a size bound, a few kB for the real-time ones; a request at its fields' bounds fits."""
    for msg_type in bus.MESSAGE_TYPES:
        limit = bus.max_payload_bytes(msg_type)
        with pytest.raises(bus.BusDecodeError, match=f"{msg_type.__name__}: payload of {limit + 1} bytes, more than"):
            bus.decode(msg_type, b" " * (limit + 1))
    assert bus.max_payload_bytes(bus.ForceCommand) <= 8192 and bus.max_payload_bytes(bus.EStop) <= 8192
    trajectory = '{"waypoints_deg": [' + ",".join(["[1.5, -2.25, 3.125]"] * 12000) + "]}"
    trajectory = trajectory[: bus.TRAJECTORY_JSON_MAX_BYTES - 2] + "]}"
    request = bus.CampaignRequest(seq=1, stamp_s=1.0, campaign_id="c-1", action="start", kind="control", law=2,
                                  trajectory_json=trajectory, parameters_toml="x" * bus.PARAMETERS_TOML_MAX_BYTES)
    assert bus.decode(bus.CampaignRequest, bus.encode(request)) == request


def test_encode_refuses_non_finite_floats() -> None:
    with pytest.raises(bus.BusEncodeError, match=r"force_N\[1\] = nan"):
        bus.encode(bus.ForceCommand(seq=0, stamp_s=0.0, force_N=[1.0, float("nan")], source="test", sender="t", epoch="e"))
    with pytest.raises(bus.BusEncodeError, match="stamp_s = inf"):
        bus.encode(bus.EStop(seq=0, stamp_s=float("inf"), engaged=False, reason=""))


def test_force_command_range_check() -> None:
    cmd = bus.ForceCommand(seq=0, stamp_s=0.0, force_N=[0.0, 10.0, 50.0], source="t", sender="t", epoch="e")
    bus.check_force_command(cmd, 3, 0.0, 50.0)
    with pytest.raises(bus.BusDecodeError, match="3 forces for 4 motors"):
        bus.check_force_command(cmd, 4, 0.0, 50.0)
    with pytest.raises(bus.BusDecodeError, match=r"force_N\[2\] = 50.0 N outside"):
        bus.check_force_command(cmd, 3, 0.0, 40.0)


def test_motor_state_range_check() -> None:
    """Audit of 2026-11-26: a state with 7 applied forces made the controller raise (the process
    ended); one with 1e308 N made it command 1e308 N, refused by the bridge tick after tick."""
    ok = sample_messages()[bus.MOTOR_STATE]
    assert isinstance(ok, bus.MotorState)
    bus.check_motor_state(ok, 4, 100.0)
    for bad, reason in [
        (msgspec.structs.replace(ok, theta_rad=[0.0] * 3), "3 angles for 4 motors"),
        (msgspec.structs.replace(ok, force_applied_N=[]), "0 applied forces for 4 motors"),
        (msgspec.structs.replace(ok, force_applied_N=[1.0] * 7), "7 applied forces"),
        (msgspec.structs.replace(ok, force_applied_N=[1e308] * 4), "force_applied_N[0] = 1e+308 N outside [0, 100.0]"),
        (msgspec.structs.replace(ok, force_applied_N=[1.0, -0.5, 1.0, 1.0]), "force_applied_N[1] = -0.5 N"),
    ]:
        with pytest.raises(bus.BusDecodeError, match=re.escape(reason)):
            bus.check_motor_state(bad, 4, 100.0)


def test_keys_and_config() -> None:
    assert bus.liveliness_key("twin", "sim-1") == "xneck/alive/twin/sim-1"
    assert bus.parse_liveliness_key("xneck/alive/twin/sim-1") == ("twin", "sim-1")
    with pytest.raises(ValueError):
        bus.liveliness_key("twin", "a/b")
    with pytest.raises(ValueError, match="protocol"):
        zenoh_config(listen=["127.0.0.1:7447"])
    with pytest.raises(ValueError, match="mode"):
        zenoh_config(mode="server")
    # Zenoh took a port over 65535: the link then failed as "nothing listens" (xneck bus check)
    with pytest.raises(ValueError, match="port must be at most 65535, got 99999"):
        zenoh_config(connect=["tcp/127.0.0.1:99999"])
    with pytest.raises(ValueError, match="port must be at most 65535"):
        zenoh_config(listen=["tls/[::1]:70000#iface=lo"])
    zenoh_config(listen=["tcp/[::1]:65535", "unixsock-stream/a:99999", "tcp/localhost"])  # fine as they are


def test_config_defaults_come_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XNECK_ZENOH_LISTEN", "tcp/127.0.0.1:7001, tcp/127.0.0.1:7002")
    monkeypatch.setenv("XNECK_ZENOH_CONNECT", "tcp/127.0.0.1:7003")
    conf = zenoh_config()
    assert msgspec.json.decode(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7001", "tcp/127.0.0.1:7002"]
    assert msgspec.json.decode(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7003"]
    assert msgspec.json.decode(conf.get_json("scouting/multicast/enabled")) is False
    assert msgspec.json.decode(zenoh_config(listen=[], connect=[]).get_json("listen/endpoints")) == []


def test_zenoh_gets_more_receive_workers_unless_the_user_chose(caplog: pytest.LogCaptureFixture) -> None:
    """tests/test_bus_dead_peers.py: each peer that stops reading can hold a receive worker 10 s."""
    env: dict[str, str] = {}
    assert zenoh_runtime_environment(env) == "(rx: (worker_threads: 8))" == env["ZENOH_RUNTIME"]
    mine = {"ZENOH_RUNTIME": "(rx: (worker_threads: 3))"}
    with caplog.at_level(logging.WARNING, logger="bridge.session"):
        assert zenoh_runtime_environment(mine) == "(rx: (worker_threads: 3))"
        assert not caplog.records
        assert zenoh_runtime_environment({"ZENOH_RUNTIME": "(app: (worker_threads: 2))"}) == "(app: (worker_threads: 2))"
    assert "sets no receive workers" in caplog.text
    assert os.environ["ZENOH_RUNTIME"]  # set on import, before any session of this process


def test_the_control_path_queue_rides_out_a_starved_sender() -> None:
    """Express real-time messages are one batch each: Zenoh's default queue of 2 batches dropped
    states whenever the sender's transmit thread was starved for ~5 ms (a CI run lost 27 states
    and the campaign's identification refused the archive). Every process queues 16 (32 ms at
    500 Hz), and a session opens with it."""
    conf = zenoh_config(listen=[], connect=[])
    sizes = msgspec.json.decode(conf.get_json("transport/link/tx/queue/size"))
    assert sizes["real_time"] == 16 and sizes["real_time"] * 0.002 >= 0.030
    assert sizes["data"] == msgspec.json.decode(zenoh.Config().get_json("transport/link/tx/queue/size"))["data"]
    zenoh.open(conf).close()  # Zenoh accepts it


def test_a_lost_link_is_retried_within_a_second() -> None:
    """Zenoh's default back-off (1 s doubling to 4 s) left a bridge started under an ``xneck estop
    engage --hold`` unlatched until the command's session came back; every process retries a
    connect endpoint from 0.1 s, at most every 1 s (docs/safety/relink.py measures it)."""
    retry = msgspec.json.decode(zenoh_config(listen=[], connect=[]).get_json("connect/retry"))
    assert (retry["period_init_ms"], retry["period_max_ms"]) == CONNECT_RETRY_MS == (100, 1000)
    assert retry["period_increase_factor"] > 1


def test_a_session_started_before_its_peer_links_once_the_peer_listens() -> None:
    port = free_tcp_port()
    heard = threading.Event()
    with open_session(listen=[], connect=[f"tcp/127.0.0.1:{port}"], credentials=None, tls=None) as early:
        early.declare_subscriber("xneck-test/relink", lambda _s: heard.set())
        threading.Event().wait(1.2)  # past Zenoh's first retry: the second is the back-off's
        with open_session(listen=[f"tcp/127.0.0.1:{port}"], connect=[], credentials=None, tls=None) as late:
            pub = late.declare_publisher("xneck-test/relink")
            assert wait_until(lambda: (pub.put(b"x"), heard.is_set())[1], 10.0), "the early session never linked"


# --- on the bus ----------------------------------------------------------------------------------


def test_messages_cross_the_bus_decoded(sessions: tuple[zenoh.Session, zenoh.Session]) -> None:
    a, b = sessions
    for key, msg in sample_messages().items():
        pub = publisher(a, key)
        sub = subscribe_latest(b, key)
        try:
            # Subscriptions propagate asynchronously: publish until the first one lands.
            assert wait_until(lambda: (pub.put(msg), sub.latest() is not None)[1]), f"nothing on {key}"
            assert sub.latest() == msg
            assert sub.stats.rejected == 0
        finally:
            sub.close()
            pub.close()
    with pytest.raises(TypeError, match="carries ForceCommand"):
        publisher(a, bus.MOTOR_COMMAND).put(sample_messages()[bus.ESTOP])


def test_malformed_commands_are_counted_and_never_crash_the_subscriber(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    a, b = sessions
    sub = subscribe_latest(b, bus.MOTOR_COMMAND, bus.ForceCommand,
                           validate=lambda c: bus.check_force_command(c, 3, 0.0, 40.0))
    good = bus.ForceCommand(seq=1, stamp_s=1.0, force_N=[1.0, 2.0, 3.0], source="test", sender="t", epoch="e")
    pub = publisher(a, bus.MOTOR_COMMAND)
    assert wait_until(lambda: (pub.put(good), sub.latest() is not None)[1])

    valid = bus.encode(good)
    bad_payloads = [
        (b"{oops", "malformed JSON"),
        (valid.replace(b'"v":2', b'"v":9'), "version 9 is not supported"),
        (valid.replace(b"[1.0,", b"[NaN,"), "malformed JSON"),
        (valid.replace(b',"source":"test"', b""), "missing required field `source`"),
        (valid.replace(b"2.0", b'"2"'), "Expected `float`, got `str`"),
        (valid.replace(b"[1.0,2.0,3.0]", b"[1.0,2.0]"), "2 forces for 3 motors"),
        (valid.replace(b"[1.0,", b"[-1.0,"), "force_N[0] = -1.0 N outside"),
        (valid.replace(b"3.0]", b"41.0]"), "force_N[2] = 41.0 N outside"),
        # audit of 2026-11-26: refused by its size, before it is copied or parsed
        (valid.replace(b'"source":"test"', b'"source":"' + b"x" * 2_000_000 + b'"'), "more than 8192"),
    ]
    for i, (payload, reason_part) in enumerate(bad_payloads, start=1):
        assert payload != valid, f"payload {i} is not malformed"
        a.put(bus.MOTOR_COMMAND, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_until(lambda: sub.stats.rejected >= i), f"payload {i} was not rejected"
        assert reason_part in sub.stats.last_reject_reason
        assert sub.stats.last_reject_reason.startswith(bus.MOTOR_COMMAND)
    # Still alive, still keeping the last valid command.
    assert sub.latest() == good
    newer = bus.ForceCommand(seq=2, stamp_s=2.0, force_N=[4.0, 5.0, 6.0], source="test", sender="t", epoch="e")
    # The publisher drops under congestion (motor keys): repeat until it lands.
    assert wait_until(lambda: (pub.put(newer), sub.wait(0.05, lambda m: m == newer) == newer)[1])
    assert sub.stats.rejected == len(bad_payloads)
    sub.close()
    pub.close()


def test_liveliness_token_appears_and_vanishes_with_its_session() -> None:
    port = free_tcp_port()
    events: list[tuple[str, str]] = []
    lock = threading.Lock()

    def on_change(sample: zenoh.Sample) -> None:
        with lock:
            events.append((str(sample.key_expr), "up" if sample.kind == zenoh.SampleKind.PUT else "down"))

    key = bus.liveliness_key("twin", "test")
    with open_session(listen=[f"tcp/127.0.0.1:{port}"], connect=[]) as console:
        console.liveliness().declare_subscriber(bus.ALIVE_ALL, on_change, history=True)
        process = open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])
        try:
            liveliness_token(process, "twin", "test")
            assert wait_until(lambda: (key, "up") in events), events
        finally:
            process.close()
        assert wait_until(lambda: (key, "down") in events), events


def test_peers_do_not_relay_so_every_pair_needs_a_link_of_its_own() -> None:
    """The premise of the layouts (server/cli/up.py, docs/bridge.md's deployment): two peers linked
    only through a third (each connected to it, neither listening where the other can reach it, as
    a BeagleBone bridge listening on its loopback alone) get none of each other's messages; once one
    of them listens, gossip links them and they do. A Zenoh upgrade that relays again shows here."""
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"

    def delivered(b_listens: list[str]) -> int:
        got: list[int] = []
        with (open_session(listen=[hub], connect=[]) as _hub, open_session(listen=[], connect=[hub]) as a,
              open_session(listen=b_listens, connect=[hub]) as b):
            sub = a.declare_subscriber("xneck/test/relay", lambda _s: got.append(1))
            pub = b.declare_publisher("xneck/test/relay")
            # Puts for 3 s: the gossip link, where there is one, comes within about a second.
            wait_until(lambda: pub.put(b"x") is None and len(got) >= 20, 3.0, 0.02)
            sub.undeclare()
        return len(got)

    assert delivered([]) == 0
    assert delivered(["tcp/127.0.0.1:0"]) >= 20


def test_a_senders_name_from_an_attachment_is_bounded_plain_text():
    """Any peer may name itself: a camera's 4000-character name (a newline and an escape in it)
    went into the camera API and the logs (review of session 41)."""
    from types import SimpleNamespace

    from bridge.session import MAX_ATTACHMENT_BYTES, NAME_MAX_CHARS, camera_attachment, camera_of, controller_of

    def sample(attachment: bytes | None) -> Any:  # a zenoh.Sample's attachment, and nothing else
        return SimpleNamespace(attachment=None if attachment is None else zenoh.ZBytes(attachment))

    assert camera_of(sample(camera_attachment("cam-lab1"))) == "cam-lab1"
    assert camera_of(sample(None)) == "" and controller_of(sample(camera_attachment("cam-lab1"))) == ""
    name = camera_of(sample(camera_attachment("cam\n\x1b[2J" + "x" * 4000)))
    assert len(name) == NAME_MAX_CHARS and name.startswith("cam  [2Jxx") and name.endswith("...")
    assert camera_of(sample(b"xneck-camera:caf\xc3\xa9")) == "caf\ufffd\ufffd"  # not ASCII: shown, not trusted
    # A 50 MB attachment was copied whole under the bridge's e-stop lock (audit of session 42).
    assert camera_of(sample(camera_attachment("c" * (MAX_ATTACHMENT_BYTES - len(b"xneck-camera:"))))).startswith("ccc")
    assert camera_of(sample(camera_attachment("c" * (MAX_ATTACHMENT_BYTES + 1)))) == ""


def test_plain_text_shows_no_bidi_override_zero_width_or_line_separator():
    """A reason with U+202E reversed the rest of the bridge's log line, a holder name with a
    zero-width space looked like another's, U+2028 was a new line to log viewers (review of session
    42): each becomes a space, as controls do; what does not encode becomes "?"."""
    spoof = "operator\u202e\u200bconsole\u2028next\u2066x\ud800\x1b[2J"
    text = bus.plain_text(spoof)
    assert text == "operator  console next x? [2J"
    assert bus.plain_text("é" * 300, 10) == "é" * 7 + "..." and bus.plain_text("x" * 10, 10) == "x" * 10
    assert bus.plain_text("x" * 10**7, 20) == "x" * 17 + "..."  # a huge one is cut first, not scanned
    # What scripts and emoji need stays (review of session 42: every format character had gone).
    for kept in ("👨\u200d👩\u200d👧 family", "می\u200cخواهم", "soft\xadhyphen", "café ✓ 🚨 a\xa0b"):
        assert bus.plain_text(kept) == kept
