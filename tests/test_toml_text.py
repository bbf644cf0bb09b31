"""TOML from outside parsed with a bound (bridge/toml_text.py; review of session 53).

``tomllib`` is quadratic in the parts of one dotted key: 32 kB of ``a.a.a…=1`` took 1.8 s and
1 GB on the console's event loop (the e-stop 7 s late), 120 kB a MemoryError. Every loader of
TOML from a request, the bus or a user's file goes through :func:`bridge.toml_text.loads`, which
refuses a key of more than 16 parts (24 with its table's header) before ``tomllib`` sees it. The bombs here are small enough
(8000 parts, 0.4 s) that a run without the guard only fails its asserts.
"""

from __future__ import annotations

import subprocess
import tomllib
from pathlib import Path

import httpx
import pytest
from server_harness import AUTH, running_server

from bridge import bus, toml_text
from controller.laws import LawConfig
from controller.prepare import Refused, prepare
from controller.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]
BOMB = "a" + ".a" * 8000 + " = 1\n"


def test_every_toml_file_of_the_repository_passes_the_guard() -> None:
    files = subprocess.run(["git", "ls-files", "*.toml"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    assert "twin/model/prototype_3x.toml" in files, files
    for name in files:
        text = (ROOT / name).read_text()
        assert toml_text.loads(text) == tomllib.loads(text), name


@pytest.mark.parametrize("text", [
    BOMB, "[" + ".".join(["t"] * 8000) + "]\n", "ok = 1\n" + BOMB,
    # a quoted first part held the '=' or ']' the first guard split the line at (review of session 53's
    # diff: 16 kB parsed in 0.7 s and 261 MB, 64 kB 20 s and 3.9 GB, a bus peer's campaign request)
    '"=".' + ".".join(["a"] * 8000) + " = 1\n",
    '["]".' + ".".join(["t"] * 8000) + "]\n",
    "[[" + " . ".join(["'t'"] * 8000) + "]]\n",
    "x = {" + ".".join(["a"] * 8000) + " = 1}\n",  # an inline table's key
    "x = [1, {y = 2, " + '."b".'.join(["a"] * 4000) + " = 1}]\n",
    # a multi-line string ending on the key's line: read as quotes and words, the key was taken for
    # part of a string or a comment (review of this session's diff)
    't = {s = """\n#""", ' + ".".join(["a"] * 4000) + " = 1}\n",
    't = {s = """\n""", ' + ".".join(["a"] * 4000) + ' = 1, z = "q"}\n',
    'x = ["""\n""", {' + ".".join(["a"] * 4000) + ' = 1}, "z"]\n',
    "t = {s = '''\n#''', " + ".".join(["a"] * 4000) + " = 1}\n",
    't = {s = """\n#""\"\"", ' + ".".join(["a"] * 4000) + " = 1}\n",
])
def test_a_key_of_thousands_of_parts_is_refused_naming_its_line(text: str) -> None:
    tomllib.loads(text.replace(".".join(["a"] * 4000), "a").replace(".".join(["t"] * 8000), "t")
                  .replace(" . ".join(["'t'"] * 8000), "t").replace("a" + ".a" * 8000, "a"))  # valid TOML but for the key
    with pytest.raises(tomllib.TOMLDecodeError, match=r"line \d+: a key of more than 16 dotted parts"):
        toml_text.loads(text)


def test_nesting_too_deep_for_the_parser_is_a_parse_error() -> None:
    with pytest.raises(tomllib.TOMLDecodeError, match="nested too deeply"):
        toml_text.loads("x = " + "[" * 5000 + "]" * 5000)


def test_a_bomb_is_refused_by_every_route_that_takes_toml_and_by_a_campaign_request(tmp_path: Path, params) -> None:
    toml = {**AUTH, "Content-Type": "application/toml"}
    with running_server(tmp_path / "data", viser=False) as (base, _app), httpx.Client(base_url=base, timeout=60) as c:
        for path in ("/api/params/bomb", "/api/truths/bomb", "/api/trajectories/bomb"):
            r = c.put(path, content=BOMB, headers=toml)
            assert r.status_code == 422 and "dotted parts" in r.text, (path, r.status_code, r.text[:300])
        r = c.post("/api/trajectories/validate", content=BOMB, headers=toml)
        assert r.status_code == 200 and not r.json()["ok"] and "dotted parts" in r.json()["message"], r.text[:300]
        assert c.get("/api/system/health").status_code == 200
    nod = Trajectory.from_degrees([[0, 0, 0], [10, 5, 0]], 1.0, 0.2, name="nod")
    req = bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="c-bomb", action="start",
                              trajectory_json=nod.to_json(), parameters_toml=BOMB)
    with pytest.raises(Refused, match="dotted parts"):
        prepare(req, params, LawConfig(law=2))


def test_a_key_and_its_tables_header_are_bounded_together_and_what_is_refused_is_said() -> None:
    """tomllib's cost grows with a table header's parts and its keys' together: 256 kB of 64-part
    keys under a 64-part header passed the first guard and parsed in 6 s (review of this session's
    diff). A key of 8 parts under a header of 16 passes (24 in all); one more part is refused."""
    header = "[" + ".".join(["h"] * 16) + "]\n"
    key = ".".join(["k"] * 8)
    assert toml_text.loads(header + key + " = 1\n")
    with pytest.raises(tomllib.TOMLDecodeError, match=r"line 2: a key of 9 dotted parts under a table header of 16"):
        toml_text.loads(header + key + ".k = 1\n")
    # a new header starts anew; arrays, values and strings are no header
    assert toml_text.loads(header + "[t]\n" + key + " = 1\n")
    assert toml_text.loads('x = [\n  [1.5, 2.5],\n]\nv = "1.2.3.4.5.6.7.8.9.10.11.12.13.14.15.16.17.18"\n'
                           's = """\na.b.c.d.e.f.g.h.i.j.k.l.m.n.o.p.q.r.s\n"""\n')
