"""Reading studies from the console (audit of 2026-11-30): what a listing, a progress and a page of rows
cost must not grow with the study (a 200,000-run directory took 8.6 s and 430 MB for one row), a summary
older than the rows on disk is not served as theirs after a restart, a failed study stays failed across a
restart, and outcomes are counted per law.

The directories are written as the study thread writes them (``study_dir`` + ``write_batch``), no Dask."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pyarrow.parquet as pq
import pytest
from browser_harness import dashboard_page, needs_chromium
from server_harness import AUTH, TOKEN, running_server, server_process, wait_until

from server.studies import execute
from server.studies.execute import read_rows, study_dir, write_batch
from server.studies.report import summarize, write_outputs
from server.studies.spec import StudyRuns, expand, study_from

DESIGN = study_from("design", samples=60, vary=("geometry.b=0.03:0.06:2",), design_configurations=10)  # 120 runs


def _design_rows(runs, feasible: float) -> list[dict]:
    return [{"run_id": r.run_id, "law": 0, "seed": r.seed, "x:geometry.b": r.values["geometry.b"],
             "feasible_fraction": feasible, "stable_fraction": 0.5, "k_min_median_N_m_per_rad": 1.0,
             "k_max_median_N_m_per_rad": 2.0, "outcome": "finished", "message": "", "run_s": 0.01, "version": "x"}
            for r in runs]


def _on_disk(root: Path, sizes: list[int], feasible: float = 0.5) -> tuple[Path, StudyRuns]:
    """DESIGN's directory under ``root`` with batches of ``sizes`` rows (as the writer leaves them)."""
    out = root / f"design-{DESIGN.digest()}"
    runs = expand(DESIGN)
    with study_dir(DESIGN, out):
        i = 0
        for n in sizes:
            write_batch(out, _design_rows(runs[i:i + n], feasible))
            i += n
    return out, runs


class _Opened:
    """Counts the Parquet files whose data (read_table) or footer (read_metadata) are read."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.tables: list[str] = []
        self.footers: list[str] = []
        table, footer = pq.read_table, pq.read_metadata

        def read_table(source, *a, **k):
            self.tables.append(str(source))
            return table(source, *a, **k)

        def read_metadata(source, *a, **k):
            self.footers.append(str(source))
            return footer(source, *a, **k)

        monkeypatch.setattr(pq, "read_table", read_table)
        monkeypatch.setattr(pq, "read_metadata", read_metadata)

        def whole_table(*_a, **_k):
            raise AssertionError("a reading route read every row")

        monkeypatch.setattr(execute, "read_rows", whole_table)
        monkeypatch.setattr(execute, "finished_ids", whole_table)

    def clear(self) -> None:
        self.tables.clear()
        self.footers.clear()


def test_a_page_of_rows_reads_only_the_batches_it_spans_and_pages_across_their_boundaries(tmp_path, monkeypatch) -> None:
    sizes = [32, 32, 7, 32, 1, 16]  # 120 rows; odd batches as a 2 s flush leaves them
    out, runs = _on_disk(tmp_path / "data" / "studies", sizes)
    expected = read_rows(out)  # the whole-table reader, before it is forbidden below
    assert len(expected) == 120
    (out / "summary.json").write_text(json.dumps(summarize(DESIGN, expected, 120)))  # its summary, up to date
    sid = out.name
    opened = _Opened(monkeypatch)
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        for offset, limit in ((0, 1), (31, 2), (60, 15), (70, 2), (71, 1), (103, 17), (119, 5), (0, 200), (120, 3),
                              (500, 1)):
            opened.clear()
            r = http.get(f"/api/studies/{sid}/results", params={"offset": offset, "limit": limit})
            assert r.status_code == 200, r.text
            page = r.json()
            assert page["total"] == 120 and page["offset"] == offset
            assert page["rows"] == expected[offset:offset + limit], (offset, limit)
            # only the batches the page spans are read
            ends = [sum(sizes[:i + 1]) for i in range(len(sizes))]
            spanned = sum(1 for i, end in enumerate(ends) if end > offset and end - sizes[i] < offset + limit)
            assert len(opened.tables) == spanned, (offset, limit, opened.tables)
        # the listing and a progress count the rows from the files' footers, once per file
        opened.clear()
        listed = http.get("/api/studies").json()["studies"]
        assert [(s["id"], s["runs_done"], s["runs_total"], s["state"]) for s in listed] == [(sid, 120, 120, "complete")]
        assert http.get(f"/api/studies/{sid}").json()["runs_done"] == 120
        assert opened.tables == [] and opened.footers == []  # counted already (the pages above), nothing read again
        # a new batch (the study resumed elsewhere): only its footer is read
        more = _design_rows(runs[:1], 0.5)
        more[0]["run_id"] = "extra"
        write_batch(out, more)
        opened.clear()
        assert http.get(f"/api/studies/{sid}/results", params={"offset": 120, "limit": 5}).json()["total"] == 121
        assert len(opened.footers) == 1 and len(opened.tables) == 1, opened.footers


def test_a_batch_replaced_in_place_is_counted_again(tmp_path) -> None:
    from server.studies.rows import count_rows, read_page

    out, _ = _on_disk(tmp_path, [32, 32])
    assert count_rows(out) == 64
    first = execute.part_files(out)[0]
    table = pq.read_table(first).slice(0, 5)
    pq.write_table(table, first)  # same name, other size
    assert count_rows(out) == 37
    assert [r["run_id"] for r in read_page(out, 0, 6)[1]] == [r["run_id"] for r in read_rows(out)[:6]]


def test_a_summary_older_than_the_rows_is_recomputed_after_a_restart(tmp_path) -> None:
    # audit: stopped at 200 (summary written), resumed, the console killed at 900: a restarted console
    # showed 900/1000 beside the summary and figures of the 200.
    root = tmp_path / "data" / "studies"
    study = study_from("design", samples=500, vary=("geometry.b=0.03:0.06:2",), design_configurations=10)
    out = root / f"design-{study.digest()}"
    runs = expand(study)
    with study_dir(study, out):
        write_batch(out, _design_rows(runs[:200], 0.2))
        write_outputs(out, study, len(runs))
        old_figure = (out / "figures" / "distributions.png").stat().st_mtime_ns
        for i in range(200, 900, 32):
            write_batch(out, _design_rows(runs[i:min(i + 32, 900)], 0.9))
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        p = http.get(f"/api/studies/{out.name}").json()
        assert (p["state"], p["runs_done"], p["runs_total"]) == ("stopped", 900, 1000)
        assert p["summary"] is None or p["summary_stale"], p  # never the 200 runs' summary as the 900's

        def fresh() -> bool:
            q = http.get(f"/api/studies/{out.name}").json()
            return q["summary"] is not None and not q["summary_stale"] and q["summary"]["runs_done"] == 900

        assert wait_until(fresh, 60)
        p = http.get(f"/api/studies/{out.name}").json()
        assert p["summary"]["metrics"]["0"]["feasible_fraction"]["median"] == 0.9
        assert (out / "figures" / "distributions.png").stat().st_mtime_ns > old_figure
        assert p["figures"]


def test_a_failed_study_stays_failed_with_its_error_after_a_restart(tmp_path, monkeypatch) -> None:
    data = tmp_path / "data"
    body = {"kind": "design", "samples": 2, "vary": ["geometry.b=0.04:0.06:2"], "design_configurations": 10}

    def lost(study, out, **_kw):
        with study_dir(study, out):
            write_batch(out, _design_rows(expand(study)[:1], 0.5))
        raise OSError("the scheduler went away")

    monkeypatch.setattr(execute, "run_study", lost)
    with running_server(data, viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        sid = http.post("/api/studies", json=body, headers=AUTH).json()["id"]
        assert wait_until(lambda: http.get(f"/api/studies/{sid}").json()["state"] == "failed", 30)
    with running_server(data, viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        p = http.get(f"/api/studies/{sid}").json()
        assert (p["state"], p["runs_done"]) == ("failed", 1), p
        assert p["error"] == "OSError: the scheduler went away"
        listed = http.get("/api/studies").json()["studies"]
        assert listed[0]["state"] == "failed" and listed[0]["error"] == p["error"]


def _half_diverged() -> tuple:
    study = study_from("control", laws=(1, 2), samples=100, vary=("friction.f_s=10%",))
    rows = [{"run_id": f"L{law}-{i}", "law": law, "run_s": 1.0, "x:friction.f_s": 1.0 + i / 1000,
             "outcome": "diverged" if (law == 1 and i % 2) else "finished", "e_mean_all_deg": 0.1 + i / 1000,
             "message": "", "version": "x"}
            for law in (1, 2) for i in range(100)]
    return study, rows


def test_outcomes_are_counted_per_law_and_each_statistic_says_over_how_many_runs() -> None:
    study, rows = _half_diverged()
    s = summarize(study, rows, 200)
    assert s["outcomes"] == {"finished": 150, "diverged": 50}
    assert s["outcomes_per_law"] == {"1": {"finished": 50, "diverged": 50}, "2": {"finished": 100}}
    assert (s["metrics"]["1"]["e_mean_all_deg"]["n"], s["metrics"]["1"]["e_mean_all_deg"]["of"]) == (50, 100)
    assert (s["metrics"]["2"]["e_mean_all_deg"]["n"], s["metrics"]["2"]["e_mean_all_deg"]["of"]) == (100, 100)


@needs_chromium
def test_the_studies_card_shows_outcomes_per_law_and_over_how_many_runs(tmp_path) -> None:
    study, rows = _half_diverged()
    out = tmp_path / "data" / "studies" / f"control-{study.digest()}"
    with study_dir(study, out):
        for law in (1, 2):
            write_batch(out, [r for r in rows if r["law"] == law])
        write_outputs(out, study, 200)
    with server_process(tmp_path / "data") as (base, _proc), \
            dashboard_page(base, block=lambda url: not url.startswith(base) or "/api/workspace" in url) as (page, errors):
        page.fill("#token", TOKEN)
        page.dispatch_event("#token", "change")
        page.wait_for_selector("#st-out table.ws-summary", timeout=30000)
        text = page.inner_text("#st-out")
        assert "law 1: 50 finished, 50 diverged" in text and "law 2: 100 finished" in text, text
        assert "50 of 100" in page.inner_text("#st-out table.ws-summary")
        assert not errors, errors


def test_a_summary_json_names_per_law_outcomes_after_write_outputs(tmp_path) -> None:
    study, rows = _half_diverged()
    with study_dir(study, tmp_path):
        write_batch(tmp_path, rows)
        write_outputs(tmp_path, study, 200)
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc["outcomes_per_law"]["1"] == {"finished": 50, "diverged": 50}


def test_stopping_a_study_that_is_not_running_says_its_state_and_a_missing_figure_is_named(tmp_path) -> None:
    """Audit: POST .../stop of a complete study answered 202 {"state": "stopping"} and nothing happened;
    GET .../figures/nosuch.png answered 404 "no study '<id>/nosuch.png'", as if the study were missing."""
    studies = tmp_path / "data" / "studies"
    complete, _runs = _on_disk(studies, [60, 60])
    with study_dir(DESIGN, complete):
        write_outputs(complete, DESIGN, 120)
    stopped_study = study_from("design", samples=60, vary=("geometry.b=0.03:0.06:2",), design_configurations=10, seed=1)
    partial = studies / f"design-{stopped_study.digest()}"
    with study_dir(stopped_study, partial):
        write_batch(partial, _design_rows(expand(stopped_study)[:5], 0.5))
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=30) as http:
        assert http.get(f"/api/studies/{complete.name}").json()["state"] == "complete"
        r = http.post(f"/api/studies/{complete.name}/stop", headers=AUTH)
        assert r.status_code == 409 and "complete" in r.json()["detail"] and complete.name in r.json()["detail"], r.text
        r = http.post(f"/api/studies/{partial.name}/stop", headers=AUTH)
        assert r.status_code == 409 and "stopped" in r.json()["detail"] and "not running" in r.json()["detail"], r.text
        assert http.post("/api/studies/design-0123456789abcdef/stop", headers=AUTH).status_code == 404
        r = http.get(f"/api/studies/{complete.name}/figures/nosuch.png")
        assert r.status_code == 404, r.text
        assert r.json()["detail"] == f"study {complete.name!r} has no figure 'nosuch.png' (its figures: distributions.png, sensitivity.png, design_maps.png)"
        r = http.get("/api/studies/design-0123456789abcdef/figures/distributions.png")
        assert r.status_code == 404 and r.json()["detail"] == "no study 'design-0123456789abcdef'", r.text
        assert http.get(f"/api/studies/{complete.name}/figures/distributions.png").status_code == 200


def test_a_summary_or_figures_folder_that_cannot_be_written_is_the_file_named(tmp_path) -> None:
    """Audit: a file named ``figures`` in the study directory gave 'cannot write DIR: File exists', and
    ``summary.json`` a folder 'cannot write DIR: Is a directory': the directory, not the file at fault."""
    out, _runs = _on_disk(tmp_path, [10])
    (out / "figures").write_text("in the way")
    with pytest.raises(OSError) as raised:
        write_outputs(out, DESIGN, 120)
    assert raised.value.filename == str(out / "figures") and raised.value.filename2 is None
    (out / "figures").unlink()
    (out / "summary.json").mkdir()
    with pytest.raises(OSError) as raised:
        write_outputs(out, DESIGN, 120)
    assert raised.value.filename == str(out / "summary.json") and raised.value.filename2 is None, raised.value


@pytest.mark.parametrize("in_the_way", ["figures", "summary.json"])
def test_the_command_line_names_the_file_in_the_way_before_anything_runs(tmp_path, in_the_way) -> None:
    from typer.testing import CliRunner

    from server.cli import app

    out = tmp_path / "study"
    out.mkdir()
    if in_the_way == "figures":
        (out / "figures").write_text("in the way")
    else:
        (out / "summary.json").mkdir()
    result = CliRunner().invoke(app, ["study", "design", "--out", str(out), "--vary", "geometry.b=0.03:0.06:2",
                                      "--configurations", "10", "--workers", "1"])
    assert result.exit_code == 2, result.output
    assert f"{out / in_the_way}:" in result.output and f"cannot write {out}:" not in result.output, result.output
    assert not (out / "runs").exists()  # said before a cluster started and runs were spent
