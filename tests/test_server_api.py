"""REST API of the console on a real server: bad input gets a 422 naming the field, auth, parameter
sets, system endpoints; and a server killed mid-campaign (recorder included) leaves an archive that
the next start recovers and marks interrupted."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import httpx
import pytest

from bridge import bus
from bridge.archive import is_complete, read_campaign
from server_harness import AUTH, running_server, server_process, wait_until


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    with running_server(tmp_path_factory.mktemp("api"), viser=False) as (base, _app):
        with httpx.Client(base_url=base, timeout=30) as c:
            yield c


def _loc(r: httpx.Response) -> list[list]:
    assert r.status_code == 422, (r.status_code, r.text)
    return [d["loc"] for d in r.json()["detail"]]


def test_system_endpoints_and_openapi(client) -> None:
    h = client.get("/api/system/health").json()
    assert h["status"] == "ok" and h["mode"] == "twin" and h["hub"].startswith("tcp/127.0.0.1:")
    assert client.get("/api/system/mode").json()["mode"] == "twin"
    assert isinstance(client.get("/api/system/processes").json()["processes"], list)
    spec = client.get("/openapi.json").json()
    for path in ("/api/campaigns", "/api/campaigns/{campaign_id}/mcap", "/api/params/{name}", "/api/system/estop"):
        assert path in spec["paths"], path
    assert client.get("/docs").status_code == 200
    assert client.get("/").status_code == 200 and "xneck console" in client.get("/").text


def test_missing_or_wrong_token_is_refused(client) -> None:
    body = {"kind": "control"}
    assert client.post("/api/campaigns", json=body).status_code == 401
    assert client.post("/api/campaigns", json=body, headers={"Authorization": "Bearer nope"}).status_code == 403
    assert client.put("/api/params/x", content=b"a = 1").status_code == 401
    assert client.post("/api/system/estop", json={"engaged": True}).status_code == 401
    assert client.delete("/api/campaigns/whatever", headers={"Authorization": "Basic abc"}).status_code in (401, 403)


def test_malformed_json_and_unknown_fields_name_the_problem(client) -> None:
    r = client.post("/api/campaigns", content=b'{"kind": "control",', headers={**AUTH, "Content-Type": "application/json"})
    assert _loc(r)[0][0] == "body"
    assert ["body", "law"] in _loc(client.post("/api/campaigns", json={"law": 7}, headers=AUTH))
    assert ["body", "kind"] in _loc(client.post("/api/campaigns", json={"kind": "dance"}, headers=AUTH))
    assert ["body", "lawz"] in _loc(client.post("/api/campaigns", json={"lawz": 2}, headers=AUTH))
    assert ["body", "truth"] in _loc(client.post("/api/campaigns", json={"truth": "perfect"}, headers=AUTH))
    r = client.post("/api/campaigns", json={"trajectory": "moonwalk"}, headers=AUTH)
    assert ["body", "trajectory"] in _loc(r) and "unknown trajectory" in r.json()["detail"][0]["msg"]
    r = client.post("/api/campaigns", json={"parameter_set": "nope"}, headers=AUTH)
    assert ["body", "parameter_set"] in _loc(r)


def test_a_waypoint_beyond_the_limits_is_refused_before_anything_moves(client) -> None:
    body = {"waypoints": {"waypoints_deg": [[0, 0, 0], [75, 0, 0], [0, 0, 0]], "durations_s": 3.0}}
    r = client.post("/api/campaigns", json=body, headers=AUTH)
    assert ["body", "waypoints"] in _loc(r)
    msg = r.json()["detail"][0]["msg"]
    assert "waypoint 1" in msg and "α1" in msg and "60" in msg
    too_fast = {"waypoints": {"waypoints_deg": [[0, 0, 0], [50, 0, 0]], "durations_s": 0.2}}
    assert "too fast" in client.post("/api/campaigns", json=too_fast, headers=AUTH).json()["detail"][0]["msg"]
    wrong_joints = {"waypoints": {"waypoints_deg": [[0, 0], [10, 0]], "durations_s": 2}}
    assert ["body", "waypoints"] in _loc(client.post("/api/campaigns", json=wrong_joints, headers=AUTH))
    assert client.get("/api/campaigns").json() == []  # nothing was started


def test_parameter_sets_upload_validation_and_active_choice(client) -> None:
    listing = client.get("/api/params").json()
    assert listing["active"] == "prototype_3x" and "prototype_3x" in listing["parameter_sets"]
    text = client.get("/api/params/prototype_3x").text
    assert "[geometry]" in text

    png = b"\x89PNG\r\n\x1a\n" + bytes(range(256))
    r = client.put("/api/params/picture", content=png, headers=AUTH)
    assert r.status_code == 422 and "not a text file" in r.json()["detail"][0]["msg"]
    r = client.put("/api/params/notes", content=b"just some notes\n", headers=AUTH)
    assert r.status_code == 422 and "TOML" in r.json()["detail"][0]["msg"]
    bad = text.replace("b = 0.05", "b = 0.5")
    r = client.put("/api/params/bad", content=bad.encode(), headers=AUTH)
    assert r.status_code == 422 and "geometry" in r.json()["detail"][0]["msg"], r.text
    assert client.put("/api/params/prototype_3x", content=text.encode(), headers=AUTH).status_code == 422
    assert ["path", "name"] in _loc(client.put("/api/params/bad%20name!", content=text.encode(), headers=AUTH))
    assert client.put("/api/params/..%2Fescape", content=text.encode(), headers=AUTH).status_code != 201

    stiffer = text.replace('name = "', 'name = "stiffer-', 1)
    r = client.put("/api/params/stiffer", content=stiffer.encode(), headers=AUTH)
    assert r.status_code == 201 and r.json()["n_joints"] == 3
    assert "stiffer" in client.get("/api/params").json()["parameter_sets"]
    assert ["body", "name"] in _loc(client.put("/api/params/active", json={"name": "ghost"}, headers=AUTH))
    assert client.put("/api/params/active", json={"name": "stiffer"}, headers=AUTH).status_code == 200
    assert client.get("/api/params/active").json()["active"] == "stiffer"
    assert client.delete("/api/params/stiffer", headers=AUTH).status_code == 409  # active
    client.put("/api/params/active", json={"name": "prototype_3x"}, headers=AUTH)
    assert client.delete("/api/params/stiffer", headers=AUTH).status_code == 204


def test_estop_is_published_and_blocks_new_campaigns(client) -> None:
    assert client.post("/api/system/estop", json={"engaged": True, "reason": "test"}, headers=AUTH).status_code == 200
    assert client.get("/api/system/health").json()["estop"]["engaged"] is True
    r = client.post("/api/campaigns", json={}, headers=AUTH)
    assert r.status_code == 409 and "e-stop" in r.json()["detail"]
    client.post("/api/system/estop", json={"engaged": False}, headers=AUTH)
    assert client.get("/api/system/health").json()["estop"]["engaged"] is False


def test_unknown_campaign_is_404(client) -> None:
    for path in ("/api/campaigns/none", "/api/campaigns/none/results", "/api/campaigns/none/mcap"):
        assert client.get(path).status_code == 404


def test_a_server_killed_mid_campaign_leaves_an_archive_the_next_start_recovers(tmp_path: Path) -> None:
    data = tmp_path / "data"
    with server_process(data) as (base, proc):
        with httpx.Client(base_url=base, timeout=30) as c:
            r = c.post("/api/campaigns", json={"kind": "control", "law": 2}, headers=AUTH)
            assert r.status_code == 201, r.text
            cid = r.json()["id"]
            assert wait_until(lambda: c.get(f"/api/campaigns/{cid}").json()["progress"] >= 0.3, 60, 0.2)
        os.killpg(proc.pid, signal.SIGKILL)  # the server, its recorder, the twin and the controller
        proc.wait(10)
    mcap = data / "campaigns" / f"{cid}.mcap"
    assert mcap.exists() and not is_complete(mcap)

    with running_server(data, viser=False) as (base, _app):
        with httpx.Client(base_url=base, timeout=30) as c:
            rec = c.get(f"/api/campaigns/{cid}").json()
            assert rec["status"] == "interrupted" and "recovered" in rec["message"]
            assert c.get("/api/campaigns", params={"status": "interrupted"}).json()[0]["id"] == cid
            download = c.get(f"/api/campaigns/{cid}/mcap")
            assert download.status_code == 200
    assert is_complete(mcap)
    campaign = read_campaign(mcap)
    assert campaign.info["outcome"] == "interrupted" and campaign.info["campaign_id"] == cid
    assert len(campaign.messages(bus.CONTROLLER_STATUS)) > 500
    assert "xneck.recovery" in campaign.metadata


def test_campaign_truth_defaults_by_kind(tmp_path) -> None:
    """A twin started for an identification campaign has the robot's damping, one for a control
    campaign the model's, unless the request says otherwise (twin/sim/truth.py)."""
    from server.campaign_request import CampaignCreate, prepare
    from server.paramsets import ParameterStore
    from server.settings import Settings

    store, settings = ParameterStore(tmp_path), Settings(data_dir=tmp_path)
    truth = lambda **kw: prepare(CampaignCreate(**kw), store, settings).spec.truth  # noqa: E731
    assert truth(kind="identification") == "robot" and truth(kind="control") == "model"
    assert truth(kind="identification", truth="model") == "model" and truth(kind="control", truth="robot") == "robot"
