"""``GET /api/campaigns/compare`` over real HTTP on real MCAP archives (issue 18): the Table-3
table of the chosen runs with their parameter sets and truths, and their traces."""

from __future__ import annotations

import json
import math
from pathlib import Path

import httpx
import pytest
from server_harness import running_server

from bridge import bus
from bridge.archive import write_campaign
from server.campaign_runner import metrics_from_archive
from server.records import CampaignIndex, CampaignRecord

NAN, INF = float("nan"), float("inf")


def _archive(path: Path, cid: str, offset_deg: float, camera_offset_deg: float) -> None:
    """A 2 s control run at 100 Hz whose α̂ lags α^d by ``offset_deg`` and the camera sees α̂ +
    ``camera_offset_deg``: e and e_α are known."""
    msgs = []
    off, cam = math.radians(offset_deg), math.radians(camera_offset_deg)
    for k in range(200):
        t = 10.0 + k / 100
        a_d = [0.3 * math.sin(t), 0.1, 0.0]
        hat = [a - off for a in a_d]
        ns = int(t * 1e9)
        msgs.append((bus.MOTOR_STATE, ns, bus.MotorState(seq=k, stamp_s=t, theta_rad=[0.0] * 4,
                                                          force_applied_N=[5.0, 6.0, 7.0, 8.0], drive="active",
                                                          epoch="e", bridge="b")))
        msgs.append((bus.MOTOR_COMMAND, ns + 1, bus.ForceCommand(seq=k, stamp_s=t, force_N=[5.0, 6.0, 7.0, 8.0],
                                                                  source="law2", sender="c", epoch="e")))
        msgs.append((bus.CONTROLLER_STATUS, ns + 2, bus.ControllerStatus(
            seq=k, stamp_s=t, law="law2", tick_s=0.01, compute_s=0.001, overruns=0, deadline_misses=0,
            saturated=[False] * 4, alpha_hat_rad=hat, alpha_d_rad=a_d, e_rad=[off] * 3, holding=False,
            campaign_id=cid, ticks=k)))
        if k % 10 == 5:
            msgs.append((bus.CAMERA_ALPHA, ns + 3, bus.CameraAlpha(seq=k, stamp_s=t, capture_stamp_s=t,
                                                                    alpha_ip_rad=[a - cam for a in hat])))
    write_campaign(path, msgs, {"campaign_id": cid, "kind": "control", "law": "law2"})


def seed_runs(data: Path) -> list[str]:
    """Two archived control runs in a console's data directory, as campaigns leave them:
    ``run-a`` (model truth, e = 1°, e_α = 0.5°) and ``run-b`` (robot truth, 2°, 1.5°)."""
    index = CampaignIndex(data / "campaigns")
    index.dir.mkdir(parents=True, exist_ok=True)
    for k, (cid, truth, off, cam) in enumerate((("run-a", "model", 1.0, 0.5), ("run-b", "robot", 2.0, 1.5))):
        _archive(index.mcap(cid), cid, off, cam)
        index.save(CampaignRecord(id=cid, kind="control", law="law2", trajectory="control_test",
                                  parameter_set="prototype_3x", target="twin", truth=truth, status="finished",
                                  created_at=f"2026-11-23T10:00:0{k}", metrics=metrics_from_archive(index.mcap(cid))))
    return ["run-a", "run-b"]


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    data = tmp_path_factory.mktemp("compare") / "data"
    seed_runs(data)
    index = CampaignIndex(data / "campaigns")
    for cid, metrics in (("edited-number", {"e_max_deg": 5, "e_mean_all_deg": 1.0}),
                         ("edited-text", {"e_max_deg": [1.0, 2.0, 3.0], "e_mean_all_deg": "x"})):
        index.save(CampaignRecord(id=cid, kind="control", law="law2", trajectory="control_test",  # edited by hand
                                  parameter_set="prototype_3x", target="twin", status="finished", metrics=metrics))
    # run-a's record with numbers JSON cannot carry, as a damaged or edited file holds them (none is
    # written: pydantic writes null): Python's json writes NaN and Infinity, the console reads them.
    record = CampaignRecord.model_validate_json(index.json("run-a").read_bytes()).model_dump()
    metrics = record["metrics"]
    metrics["e_mean_all_deg"], metrics["force_mean_all_N"], metrics["saturated_ticks"] = NAN, -INF, NAN
    metrics["e_max_deg"][1], metrics["e_mean_deg"][0] = NAN, INF
    index.json("not-finite").write_text(json.dumps({**record, "id": "not-finite", "metrics": metrics}))
    # an identification whose c_a(4) was held at its bound (0): no σ, relative σ null (fresh-user audit
    # of 2026-12-01: its /results was a 500 and the dashboard showed no table)
    held = [{"name": "c_a(4)", "value": 0.0, "sigma": None, "relative_sigma": None, "badly_identified": True,
             "reason": "held at its bound"},
            {"name": "k(1)", "value": 5000.0, "sigma": 50.0, "relative_sigma": 0.01, "badly_identified": False}]
    index.save(CampaignRecord(id="held-at-bound", kind="identification", law="law1", trajectory="identification",
                              parameter_set="prototype_3x", target="twin", status="finished",
                              identification={"table_2": {"parameters": held, "estimator": "auto"}}))
    for cid in ("no-archive", "damaged"):  # a record whose archive is missing, one whose archive is no MCAP
        index.save(CampaignRecord(id=cid, kind="control", law="law2", trajectory="control_test",
                                  parameter_set="prototype_3x", target="twin", status="finished"))
    index.mcap("damaged").write_bytes(b"no archive at all")
    with running_server(data, viser=False) as (base, _app), httpx.Client(base_url=base, timeout=10) as client:
        yield client


def test_compare_returns_the_table_3_rows_of_the_chosen_runs_with_their_truths(console):
    r = console.get("/api/campaigns/compare", params={"ids": "run-a,run-b"})
    assert r.status_code == 200, r.text
    table = r.json()["table"]
    rows = {row[0]: dict(zip(table["columns"], row)) for row in table["rows"]}
    assert rows["run-a"]["truth"] == "model" and rows["run-b"]["truth"] == "robot"
    assert rows["run-a"]["parameter set"] == "prototype_3x" and rows["run-a"]["control law"] == "law2"
    assert rows["run-a"]["e mean (deg)"] == pytest.approx(1.0, abs=1e-3)
    assert rows["run-b"]["e mean (deg)"] == pytest.approx(2.0, abs=1e-3)
    assert rows["run-b"]["e_α mean (deg)"] == pytest.approx(1.5, abs=1e-2)
    assert "traces" not in r.json()


def test_compare_traces_overlay_each_runs_series(console):
    r = console.get("/api/campaigns/compare", params={"ids": "run-b,run-a", "traces": "true"}).json()
    assert [row[0] for row in r["table"]["rows"]] == ["run-b", "run-a"]  # the order asked for
    b = r["traces"]["run-b"]
    assert b["t_s"][0] == 0.0 and len(b["alpha_d_deg"]) == 3 and len(b["force"]["force_N"]) == 4
    assert b["e_deg"][0][0] == pytest.approx(2.0) and b["camera"]["e_alpha_deg"][0][0] == pytest.approx(1.5, abs=1e-3)
    assert b["alpha_d_deg"][1][0] - b["alpha_hat_deg"][1][0] == pytest.approx(2.0)


def test_traces_are_kept_beside_the_archive_and_computed_again_when_it_changes(tmp_path):
    """A 600 s campaign's traces took 13-15 s and ~0.8 GB per request, every time a comparison was
    opened (audit of 2026-11-30): kept in its figures folder while newer than the archive."""
    from server.compare import cached_traces, traces

    index = CampaignIndex(tmp_path / "campaigns")
    mcap, folder = index.mcap("run-a"), index.figures("run-a")
    _archive(mcap, "run-a", 1.0, 0.5)
    first = cached_traces(mcap, folder)
    assert first == traces(mcap) and (folder / "traces-800.json").is_file()
    mcap.write_bytes(b"no longer an archive")  # newer than the kept traces: read again, and refused
    with pytest.raises(Exception, match="not an MCAP file"):
        cached_traces(mcap, folder)
    _archive(mcap.with_suffix(".new"), "run-a", 2.0, 0.5)
    mcap.with_suffix(".new").replace(mcap)
    (folder / "traces-800.json").write_text('{"t_s": [')  # damaged, and older: computed again, kept again
    again = cached_traces(mcap, folder)
    assert again == traces(mcap) and again["e_deg"][0][0] == pytest.approx(2.0)
    kept = (folder / "traces-800.json").read_text()
    doc = json.loads(kept)
    doc["traces"]["e_deg"][0][0] = 99.0  # what is kept is what is served while the archive is unchanged
    (folder / "traces-800.json").write_text(json.dumps(doc))
    assert cached_traces(mcap, folder)["e_deg"][0][0] == 99.0
    mcap.unlink()  # a missing archive is an error, kept traces or not
    with pytest.raises(FileNotFoundError):
        cached_traces(mcap, folder)


@pytest.mark.parametrize(("ids", "code"), [("run-a", 422), ("run-a,run-a", 422), ("run-a,b,c,d,e", 422),
                                           ("run-a,nope", 404), ("run-a,../../etc", 404)])
def test_compare_refuses_what_it_cannot_compare(console, ids, code):
    assert console.get("/api/campaigns/compare", params={"ids": ids}).status_code == code


@pytest.mark.parametrize(("edited", "said"), [("edited-number", "metrics.e_max_deg"),
                                              ("edited-text", "metrics.e_mean_all_deg")])
def test_a_hand_edited_record_whose_metrics_are_not_numbers_is_a_422_naming_them(console, edited, said):
    # audit of 2026-11-26: max() of a number was a 500.
    r = console.get("/api/campaigns/compare", params={"ids": f"run-a,{edited}"})
    assert r.status_code == 422, r.text
    assert edited in r.json()["detail"] and said in r.json()["detail"], r.text


def test_numbers_json_cannot_carry_answer_null_not_a_500(console):
    """Review of session 53: a NaN or infinity in a record read from disk, which JSON cannot carry.
    Each is null (FastAPI writes a route's answer through its return annotation with pydantic,
    which writes them as null: a route without one would be a 500), the rest as it was. The
    largest e of joints one of which is unknown is unknown: max() with a NaN gave 1.0 here."""
    r = console.get("/api/campaigns/compare", params={"ids": "run-a,not-finite"})
    assert r.status_code == 200, r.text
    table = r.json()["table"]
    a, bad = (dict(zip(table["columns"], row)) for row in table["rows"])
    assert bad["e mean (deg)"] is None and bad["force mean (N)"] is None and bad["saturated ticks"] is None, bad
    assert bad["e max (deg)"] is None  # one joint's unknown: the largest is unknown too
    assert bad["e_α mean (deg)"] == a["e_α mean (deg)"] is not None
    r = console.get("/api/campaigns/not-finite/results")
    assert r.status_code == 200, r.text
    metrics = r.json()["metrics"]
    assert metrics["e_mean_all_deg"] is None and metrics["force_mean_all_N"] is None and metrics["saturated_ticks"] is None
    assert metrics["e_max_deg"][1] is None and metrics["e_mean_deg"][0] is None and metrics["e_max_deg"][0] > 0
    errors = next(t for t in r.json()["tables"] if t["title"] == "Errors per joint (deg)")
    assert errors["rows"][0][1] is None and errors["rows"][1][2] is None, errors
    assert console.get("/api/campaigns/not-finite").json()["metrics"]["e_mean_all_deg"] is None


@pytest.mark.parametrize(("cid", "said"), [("no-archive", "campaign no-archive has no archive"),
                                           ("damaged", "not an MCAP file")])
def test_an_unreadable_archive_is_a_422_that_does_not_name_the_data_directory(console, cid, said):
    """Review of session 53: the 422 carried the exception's text, which for a record without an
    archive was ``[Errno 2] No such file or directory: '/…/campaigns/x.mcap'`` (an open GET
    telling the data directory). Now the campaign and the reason, no path; a figure's too."""
    r = console.get("/api/campaigns/compare", params={"ids": f"run-a,{cid}", "traces": "true"})
    assert r.status_code == 422 and said in r.json()["detail"] and cid in r.json()["detail"], r.text
    assert "/" not in r.json()["detail"] and "campaigns" not in r.json()["detail"], r.text
    r = console.get(f"/api/campaigns/{cid}/figures/tracking.png")
    assert r.status_code == 422 and cid in r.json()["detail"] and "/" not in r.json()["detail"], r.text


def test_a_flood_of_open_archive_reads_never_delays_the_estop(tmp_path, monkeypatch):
    """Review of session 53: a compare GET with traces needs no token and read its archives on
    anyio's default pool (40 threads), each request the whole archive again while the first had
    not kept it; the e-stop's POST needed that pool for its token check and its publication, and
    45 such GETs delayed it 7.3 s. Here 50 compare GETs and 6 figure GETs over 6 archives, every
    archive read held in progress: the e-stop is answered and engaged while they are held, at most
    2 reads ran at once, and once released each archive was read once for its traces and once
    for its figure (the requests for the same archive waited, then used what the first kept)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from server_harness import AUTH, running_server, wait_until

    from server import compare, results, routes_campaigns, routes_compare

    data = tmp_path / "data"
    index = CampaignIndex(data / "campaigns")
    index.dir.mkdir(parents=True, exist_ok=True)
    ids = [f"run-{k}" for k in range(6)]
    for k, cid in enumerate(ids):
        _archive(index.mcap(cid), cid, 1.0 + k, 0.5)
        index.save(CampaignRecord(id=cid, kind="control", law="law2", trajectory="control_test",
                                  parameter_set="prototype_3x", target="twin", truth="model", status="finished",
                                  created_at=f"2026-11-23T10:00:0{k}"))
    release = threading.Event()
    lock = threading.Lock()
    running, peak, arrived = [0], [0], [0]
    reads: dict[tuple[str, str], int] = {}

    def held(what: str, real):
        def read(mcap: Path, *args):
            with lock:
                running[0] += 1
                peak[0] = max(peak[0], running[0])
                reads[(what, mcap.stem)] = reads.get((what, mcap.stem), 0) + 1
            try:
                release.wait(60)
                return real(mcap, *args)
            finally:
                with lock:
                    running[0] -= 1
        return read

    def counted(real):
        def call(*args):
            with lock:
                arrived[0] += 1  # a request past its lookups, at its archive reads
            return real(*args)
        return call

    monkeypatch.setattr(compare, "traces", held("traces", compare.traces))
    monkeypatch.setattr(routes_campaigns, "render_figure", held("figure", results.render_figure))
    monkeypatch.setattr(routes_compare, "compare_table", counted(routes_compare.compare_table))
    monkeypatch.setattr(routes_campaigns, "_record", counted(routes_campaigns._record))
    urls = [f"/api/campaigns/compare?ids={ids[k % 6]},{ids[(k + 1) % 6]}&traces=true" for k in range(50)]
    urls += [f"/api/campaigns/{cid}/figures/tracking.png" for cid in ids[:3] * 2]
    with (running_server(data, viser=False) as (base, app), httpx.Client(base_url=base, timeout=60) as client,
          ThreadPoolExecutor(len(urls)) as pool):
        try:
            gets = [pool.submit(httpx.get, base + url, timeout=90) for url in urls]
            assert wait_until(lambda: arrived[0] == len(urls) and running[0] >= 2, 30), (arrived, running)
            try:  # a bound, not a time asserted: before, it was answered only once the reads were released
                estop = client.post("/api/system/estop", json={"engaged": True, "reason": "flood"}, headers=AUTH,
                                    timeout=20)
            except httpx.TimeoutException:
                estop = None
            assert estop is not None and estop.status_code == 200, "the e-stop waited for the archive reads"
            assert not release.is_set() and running[0] == 2  # the reads still held, two at most
            assert app.state.campaigns.estop_engaged is True
            assert client.get("/api/system/health", timeout=20).json()["estop"]["engaged"] is True
            assert wait_until(lambda: getattr(app.state.live.values.get("estop"), "engaged", None) is True, 10), \
                "the e-stop was not on the bus"
        finally:
            release.set()
        answers = [g.result() for g in gets]
    assert all(r.status_code == 200 for r in answers), [r.text[:200] for r in answers if r.status_code != 200]
    assert all(set(r.json()["traces"]) == set(u.split("=")[1].split("&")[0].split(","))
               for r, u in zip(answers, urls) if "compare" in u)
    assert peak[0] == 2, peak
    assert reads == {**{("traces", cid): 1 for cid in ids}, **{("figure", cid): 1 for cid in ids[:3]}}, reads


def test_an_identification_with_a_parameter_held_at_its_bound_has_its_tables(console):
    r = console.get("/api/campaigns/held-at-bound/results")
    assert r.status_code == 200, r.text
    table = next(t for t in r.json()["tables"] if t["title"].startswith("Table 2"))
    rows = {row[0]: row for row in table["rows"]}
    assert rows["c_a(4)"][1:5] == [0.0, None, None, "held at its bound"], rows
    assert rows["k(1)"][3] == 1.0, rows
