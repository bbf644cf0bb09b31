"""``POST /api/jog`` over real HTTP (issue 18): what is refused, and why, before anything moves.
The jog that moves the neck is in tests/test_console_browser.py (a real stack)."""

from __future__ import annotations

import httpx
import pytest
from server_harness import AUTH, running_server


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    with running_server(tmp_path_factory.mktemp("jog") / "data", viser=False) as (base, app), \
            httpx.Client(base_url=base, timeout=10) as client:
        yield client, app


def test_a_jog_out_of_the_joint_limits_is_refused_with_the_checkers_message(console):
    client, _ = console
    r = client.post("/api/jog", json={"alpha_deg": [0, 75, 0]}, headers=AUTH)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["body", "alpha_deg"]
    assert "out of the joint limits" in detail["msg"] and "α2 = 75°" in detail["msg"], detail
    r = client.post("/api/jog", json={"alpha_deg": [0, 0]}, headers=AUTH)
    assert r.status_code == 422 and "wrong number of joints" in r.json()["detail"][0]["msg"], r.text
    for bad in (b'{"alpha_deg": []}', b'{"alpha_deg": ["x", 0, 0]}', b'{"alpha": [0, 0, 0]}',
                b'{"alpha_deg": [1e400, 0, 0]}', b'{"alpha_deg": [NaN, 0, 0]}'):
        r = client.post("/api/jog", content=bad, headers={**AUTH, "Content-Type": "application/json"})
        assert r.status_code == 422, (bad, r.text)


def test_a_jog_needs_the_token_and_a_controller_service(console):
    client, _ = console
    assert client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}).status_code == 401
    r = client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH)
    assert r.status_code == 503 and "no controller service" in r.json()["detail"], r.text


def test_a_jog_is_refused_while_the_estop_is_engaged(console):
    client, _ = console
    assert client.post("/api/system/estop", json={"engaged": True, "reason": "test"}, headers=AUTH).status_code == 200
    try:
        r = client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH)
        assert r.status_code == 409 and "release the e-stop" in r.json()["detail"] and "test" in r.json()["detail"]
    finally:
        client.post("/api/system/estop", json={"engaged": False, "reason": "test"}, headers=AUTH)
    assert client.post("/api/jog", json={"alpha_deg": [5, 0, 0]}, headers=AUTH).status_code == 503
