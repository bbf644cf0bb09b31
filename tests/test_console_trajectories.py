"""``/api/trajectories`` over real HTTP (issue 18): the library (list, get, put, delete; JSON or
TOML), names that cannot leave the library's directory, and the checks a campaign start runs."""

from __future__ import annotations

import json

import httpx
import pytest
from server_harness import AUTH, running_server, wait_until

NOD = {"name": "nod", "waypoints_deg": [[0, 0, 0], [20, 10, 0], [0, 0, 0]], "durations_s": 2.0, "dwell_s": 0.5}
NOD_TOML = b'name = "nod"\nwaypoints_deg = [[0, 0, 0], [20, 10, 0], [0, 0, 0]]\ndurations_s = 2.0\ndwell_s = 0.5\n'


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    data = tmp_path_factory.mktemp("traj") / "data"
    with running_server(data, viser=False) as (base, _app), httpx.Client(base_url=base, timeout=10) as client:
        yield client, data


def test_the_library_saves_lists_gets_and_deletes_json_and_toml(console):
    client, data = console
    assert client.put("/api/trajectories/nod", json=NOD, headers=AUTH).status_code == 201
    r = client.put("/api/trajectories/nod-toml", content=NOD_TOML, headers={**AUTH, "Content-Type": "application/toml"})
    assert r.status_code == 201, r.text
    listed = {t["name"]: t for t in client.get("/api/trajectories").json()["trajectories"]}
    assert listed["control_test"]["builtin"] and listed["nod"]["duration_s"] == pytest.approx(5.5)
    got = client.get("/api/trajectories/nod-toml").json()
    assert got["waypoints_deg"] == NOD["waypoints_deg"] and got["name"] == "nod-toml"
    assert (data / "trajectories" / "nod.json").is_file()
    assert client.delete("/api/trajectories/nod", headers=AUTH).status_code == 204
    assert client.get("/api/trajectories/nod").status_code == 404
    assert client.delete("/api/trajectories/control_test", headers=AUTH).status_code == 409
    assert client.put("/api/trajectories/x", json=NOD).status_code == 401


@pytest.mark.parametrize("name", ["..", ".hidden", "a/b", "..%2F..%2Fetc%2Fpasswd", "a" * 65, "x y", "control_test"])
def test_names_cannot_leave_the_library_or_replace_a_builtin(console, name):
    client, data = console
    r = client.put(f"/api/trajectories/{name}", json=NOD, headers=AUTH)
    assert r.status_code in (404, 405, 422), (name, r.status_code, r.text)
    assert not any(p.name.startswith(".") and p.suffix == ".json" for p in data.rglob("*")), list(data.rglob("*"))
    assert not (data.parent / "etc").exists()


def test_the_checks_of_a_campaign_start_refuse_with_the_checkers_message(console):
    client, _ = console
    far = {**NOD, "waypoints_deg": [[0, 0, 0], [20, 75, 0], [0, 0, 0]]}
    r = client.put("/api/trajectories/far", json=far, headers=AUTH)
    assert r.status_code == 422 and "out of the joint limits" in r.json()["detail"][0]["msg"], r.text
    v = client.post("/api/trajectories/validate", json=far, headers=AUTH).json()
    assert not v["ok"] and "waypoint 1" in v["message"] and "α2 = 75°" in v["message"], v
    assert len(v["preview"]["alpha_deg"]) == 3 and max(v["preview"]["alpha_deg"][1]) == pytest.approx(75)
    fast = {**NOD, "durations_s": 0.2}
    v = client.post("/api/trajectories/validate", json=fast, headers=AUTH).json()
    assert not v["ok"] and "too fast" in v["message"] and "needs at least" in v["message"], v
    v = client.post("/api/trajectories/validate", json=NOD, headers=AUTH).json()
    assert v["ok"] and v["preview"]["duration_s"] == pytest.approx(5.5), v
    v = client.post("/api/trajectories/validate", json={"waypoints_deg": [[0, 0]], "bogus": 1}, headers=AUTH).json()
    assert not v["ok"] and v["preview"] is None and "bogus" in v["message"], v


def test_a_total_duration_that_overflows_is_refused_not_a_500(console):
    """Audit of 2026-11-27: moves and dwells each finite, their sum inf: validate's preview asked
    time_grid for an infinite step and the console answered 500."""
    client, _ = console
    huge = {"waypoints_deg": [[0, 0, 0], [0, 0, 0], [0, 0, 0]], "durations_s": [1e308, 1e308]}
    r = client.post("/api/trajectories/validate", json=huge, headers=AUTH)
    assert r.status_code == 200, r.text
    v = r.json()
    assert not v["ok"] and v["preview"] is None and "not finite" in v["message"], v
    r = client.put("/api/trajectories/huge", json=huge, headers=AUTH)
    assert r.status_code == 422 and "not finite" in r.json()["detail"][0]["msg"], r.text


def test_a_stored_file_that_does_not_read_is_a_422_not_no_such_trajectory(console):
    """Audit of 2026-11-27: a file of the library that is not JSON (edited by hand, cut short)
    answered 404 "no trajectory", while the list showed it with its error."""
    client, data = console
    (data / "trajectories").mkdir(parents=True, exist_ok=True)
    (data / "trajectories" / "broken.json").write_bytes(b'{"waypoints_deg": [[0, 0')
    r = client.get("/api/trajectories/broken")
    assert r.status_code == 422 and "stored trajectory 'broken'" in r.json()["detail"], r.text
    assert client.get("/api/trajectories/nothing-here").status_code == 404
    assert client.get("/api/trajectories/.hidden").status_code == 404
    assert client.get("/api/trajectories/control_test").status_code == 200


def test_a_refused_trajectory_of_a_thousand_joints_gets_no_preview(console):
    """Audit of 2026-11-28: a 40 KB body of 2 waypoints x 10,000 joints was refused ("the robot
    has 3") with a 160 MB preview, 2.5 GB of the console's memory. Past PREVIEW_MAX_JOINTS there is
    no preview to draw."""
    client, _ = console
    wide = {"name": "wide", "waypoints_deg": [[0.0] * 1000, [1.0] * 1000], "durations_s": [1e6]}
    r = client.post("/api/trajectories/validate", json=wide, headers=AUTH)
    assert r.status_code == 200, r.text
    v = r.json()
    assert v["ok"] is False and "1000" in v["message"] and v["preview"] is None
    assert len(r.content) < 10_000
    assert client.post("/api/trajectories/validate", json=NOD, headers=AUTH).json()["preview"]["alpha_deg"]


def test_a_figure_of_an_archive_with_two_thousand_joints_is_refused_at_once(tmp_path):
    """Audit of 2026-11-28: a first controller status of 2,000 angles (a 4 KB payload) drew
    2,000 axes for 32 s under the figures' lock, every other figure waiting; the archive is
    hostile input."""
    from bridge import bus
    from bridge.archive import write_campaign
    from server.results import FIGURE_MAX_JOINTS, render_figure

    n = 2000
    status = bus.ControllerStatus(seq=1, stamp_s=0.0, law="law2", tick_s=0.002, compute_s=0.0, overruns=0,
                                  deadline_misses=0, saturated=[False] * 4, alpha_hat_rad=[0.0] * n,
                                  alpha_d_rad=[0.0] * n, e_rad=[0.0] * n, holding=False)
    path = write_campaign(tmp_path / "wide.mcap", [(bus.CONTROLLER_STATUS, 1, status)], {"campaign_id": "wide"})
    with pytest.raises(ValueError, match=f"2000 joints.*at most {FIGURE_MAX_JOINTS}"):
        render_figure(path, "tracking", tmp_path / "fig.png")
    assert not (tmp_path / "fig.png").exists()


def test_a_library_trajectory_starts_as_a_campaign_by_name_with_the_same_checks(console):
    """Audit of 2026-11-29: ``POST /api/campaigns {"trajectory": "nod"}`` for a trajectory saved with
    ``PUT /api/trajectories/nod`` (201) answered 422 "unknown trajectory 'nod'; known:
    identification, control_test". A library name starts it as its waypoints sent inline would,
    the same checks refusing what they refuse; a name in neither is a 422 listing both."""
    client, data = console
    assert client.put("/api/trajectories/nod-run", json=NOD, headers=AUTH).status_code == 201
    r = client.post("/api/campaigns", json={"kind": "control", "trajectory": "nod-run"}, headers=AUTH, timeout=60)
    assert r.status_code == 201, r.text
    rec = r.json()
    try:
        assert rec["trajectory"] == "nod-run" and rec["trajectory_spec"]["waypoints_deg"] == NOD["waypoints_deg"], rec
    finally:
        client.post(f"/api/campaigns/{rec['id']}/stop", headers=AUTH, timeout=60)
        assert wait_until(lambda: client.get(f"/api/campaigns/{rec['id']}").json()["status"] != "running", 60, 0.3)
    # Stored beside the library's checks (by hand): the campaign's own checks still refuse it.
    far = {**NOD, "name": "far-by-hand", "waypoints_deg": [[0, 0, 0], [20, 75, 0], [0, 0, 0]]}
    (data / "trajectories" / "far-by-hand.json").write_text(json.dumps(far))
    r = client.post("/api/campaigns", json={"trajectory": "far-by-hand"}, headers=AUTH, timeout=60)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "trajectory"], r.text
    assert "out of the joint limits" in r.json()["detail"][0]["msg"], r.text
    r = client.post("/api/campaigns", json={"trajectory": "no-such-one"}, headers=AUTH, timeout=60)
    msg = r.json()["detail"][0]["msg"]
    assert r.status_code == 422 and "unknown trajectory 'no-such-one'" in msg and "nod-run" in msg, r.text
    assert "control_test" in msg, msg


@pytest.fixture(scope="module")
def no_room_console(tmp_path_factory):
    """A console whose free-space floor no disk meets (tests/test_fuzz_api.py's device): a campaign
    body that passes every check is answered 507 instead of spawning a twin."""
    data = tmp_path_factory.mktemp("strict") / "data"
    with running_server(data, viser=False, min_free_mb=1e12) as (base, _app), \
            httpx.Client(base_url=base, timeout=10) as client:
        yield client


@pytest.mark.parametrize("body", [
    {"waypoints": {**NOD, "waypoints_deg": [[0, 0, 0], [True, 10, 0], [0, 0, 0]]}},
    {"waypoints": {**NOD, "waypoints_deg": [[0, 0, 0], ["8", 10, 0], [0, 0, 0]]}},
    {"waypoints": {**NOD, "durations_s": "3"}},
    {"waypoints": {**NOD, "dwell_s": [False, 0, 0]}},
    {"waypoints": NOD, "no_pulleys": "true"},
    {"waypoints": NOD, "seed": "5"},
    {"waypoints": NOD, "law": True},
    {"kind": "identification", "creep_time_s": True},
], ids=["bool-angle", "string-angle", "string-duration", "bool-dwell", "string-bool", "string-seed", "bool-law",
        "bool-creep"])
def test_a_campaign_body_of_the_wrong_types_is_refused_not_coerced(no_room_console, body):
    """Input audit: POST /api/campaigns took true as 1°, "8" as 8° and "durations_s": "3" as 3 s and
    started the campaign (201), where /api/trajectories refuses the same body ("never silently
    changed", server/campaign_request.py). 422 naming the field, like every other route."""
    client = no_room_console
    r = client.post("/api/campaigns", json=body, headers=AUTH)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail and all(d["loc"][0] == "body" for d in detail), detail
    if "waypoints" in body and body["waypoints"] is not NOD:  # the library refuses the same trajectory
        assert client.put("/api/trajectories/typed", json=body["waypoints"], headers=AUTH).status_code == 422
    assert client.post("/api/campaigns", json={"waypoints": NOD}, headers=AUTH).status_code == 507  # well typed


@pytest.mark.parametrize("name", ["nod\u202e", "a\x00b", "a\nb", "a\u200bb"])
def test_a_trajectory_name_with_a_control_or_format_character_is_a_422(no_room_console, name):
    """Input audit: a NUL, a newline or a bidi override (U+202E, which reorders what the console
    and the CLI show) in a trajectory's name reached the campaign's record and archive."""
    client = no_room_console
    body = {**NOD, "name": name}
    r = client.post("/api/campaigns", json={"waypoints": body}, headers=AUTH)
    bad = next(c for c in name if not c.isalnum())
    assert r.status_code == 422 and f"U+{ord(bad):04X}" in r.text, r.text
    assert client.put("/api/trajectories/named", json=body, headers=AUTH).status_code == 422
    v = client.post("/api/trajectories/validate", json=body, headers=AUTH).json()
    assert not v["ok"] and "name" in v["message"], v
    from urllib.parse import quote

    assert client.put(f"/api/trajectories/{quote(name)}", json=NOD, headers=AUTH).status_code in (404, 422)
