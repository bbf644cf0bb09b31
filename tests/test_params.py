"""Parameter files (issue 2): defaults, user files, overrides and clear errors."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest

from twin.model.params import ParameterError, load_params, params_from_dict


def test_default_is_the_3x_prototype(params):
    assert params.n_joints == 3 and params.n_cables == 4
    assert (params.geometry.L, params.geometry.b, params.geometry.r) == (0.100, 0.050, 0.0046)
    assert params.springs.k_left == (600.0, 200.0, 200.0) and params.springs.l0[0] == 0.046
    assert params.friction.f_s == (14.42, 17.65, 18.77, 16.18) and params.friction.c_s == 0.5
    assert params.cables.variable.lam == (103.3, 88.7, 53.2, 120.9)
    assert (params.limits.t_min, params.limits.f_min) == (8.5, 2.0)
    assert params.routes[3] == ((0, "c"), (1, "c"), (2, "a"))


def test_round_trip_through_a_user_file(params, tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text(params.to_toml())
    assert load_params(path) == params
    tuned = load_params(path, overrides={"springs.l0": [0.05, 0.05, 0.05], "cables.model": "linear"})
    assert tuned.springs.l0 == (0.05, 0.05, 0.05) and tuned.cables.model == "linear"
    with pytest.raises(AttributeError):
        tuned.geometry.L = 1.0  # immutable


@pytest.mark.parametrize(
    "override, key, reason",
    [
        ({"geometry.b": 0.1}, "geometry", "must be smaller than L"),
        ({"geometry.L": "long"}, "geometry.L", "Expected `float`, got `str`"),
        ({"springs.k_right": [600.0, -1.0, 200.0]}, "springs", "k_right must be >= 0"),
        ({"bars.m_top": [0.01, 0.01]}, "bars.m_top", "expected one per joint"),
        ({"friction.f_s": [1.0, 2.0, 3.0]}, "friction.f_s", "expected one per cable"),
        ({"bars.m_diagonal": [0.009, -0.009, 0.009]}, "bars", "m_diagonal must be >= 0"),
        ({"cables.routing": ["1b", "1x"]}, "routing[1]", "is not <joint number"),
        ({"cables.routing": ["1b", "1d 2b", "1d 2d 4b", "1c 2c 3a"]}, "routing[2]", "n_joints = 3"),
        ({"cables.model": "rubber"}, "cables.model", "Invalid enum value 'rubber'"),
        ({"limits.f_max": 1.0}, "limits", "must exceed f_min"),
        ({"motors.I_a": float("nan")}, "motors", "I_a must be finite"),
        ({"geometry.n_joints": True}, "geometry.n_joints", "Expected `int`, got `bool`"),
        # audit of 2026-11-26: beyond what the twin's 2 ms step integrates (tests/test_sim.py
        # checks the bounds themselves run), a typo froze the twin at its flat singularity or
        # reported 8e7 N of tension for 2 N commanded; a massless neck raised LinAlgError.
        ({"springs.k_left": [1e12, 1e12, 1e12]}, "springs", "k_left must be <= 1e+06 N/m"),
        ({"cables.variable.k": [1e15] * 4}, "cables.variable", "k must be <= 1e+07 N/m"),
        ({"cables.linear.k": [1e9] * 4}, "cables.linear", "k must be <= 1e+07 N/m"),
        ({"bars.m_diagonal": [0.0] * 3, "bars.I_diagonal": [0.0] * 3, "bars.m_top": [0.0] * 3, "bars.I_top": [0.0] * 3},
         "bars", "a neck without any mass or inertia"),
        # user audit: a study with friction.f_s = 6e299 N ran a twin stuck at rest, 'finished'; the
        # prototype's motors pull 5 A × 0.0367 N·m/A × 25 / 0.020 m = 229.4 N at most
        ({"friction.f_s": [6e299] * 4}, "friction.f_s", "must be below the motors' peak force at the cable, 229.4 N"),
        ({"friction.f_s": [14.0, 14.0, 230.0, 14.0]}, "friction.f_s", "229.4 N"),
        ({"motors.current_max": 0.3}, "friction.f_s", "peak force at the cable, 13.76 N"),
        # audit of session 46: a study with λ = 1e12 1/m ran a twin at 0.05 N of tension for 10-90 N
        # commanded, 'finished'; eq. 54's stiffness at f_max, (k + λ·f_max)²/k, within 1e7 N/m
        ({"cables.variable.lambda": [1e12] * 4}, "cables.variable.lambda",
         "λ <= 2265, 2262, 2434, 1362 1/m for cable(s) 1, 2, 3, 4"),
        ({"cables.variable.lambda": [103.3, 88.7, 53.2, 1400.0]}, "cables.variable.lambda", "1362 1/m for cable(s) 4"),
    ],
)
def test_bad_values_name_the_key_and_the_reason(override, key, reason):
    with pytest.raises(ParameterError) as err:
        load_params(overrides=override)
    assert key in str(err.value) and reason in str(err.value)


def test_a_bad_set_value_is_said_to_be_the_set_value_not_the_parameter_file():
    """Audit: ``--set friction.f_s=nan`` said '<package>/prototype_3x.toml: friction.f_s: Expected
    `array`, got `float`', which read as if the shipped file were broken."""
    with pytest.raises(ParameterError) as err:
        load_params(overrides={"friction.f_s": float("nan")})
    text = str(err.value)
    assert text.startswith("--set friction.f_s=nan: "), text
    assert "a list of 4 values" in text and "write --set friction.f_s=[" in text, text
    assert "friction.f_s must be finite, not nan" in text, text
    with pytest.raises(ParameterError) as err:
        load_params(overrides={"friction.f_s": [1.0, float("inf"), 1.0, 1.0]})
    assert str(err.value).startswith("--set friction.f_s=[1.0, inf, 1.0, 1.0]: ") and "finite" in str(err.value)
    with pytest.raises(ParameterError) as err:
        load_params(overrides={"geometry.b": [0.01, 0.02]})
    assert str(err.value).startswith("--set geometry.b=[0.01, 0.02]: ") and "a single value" in str(err.value)
    with pytest.raises(ParameterError) as err:  # a value of the right shape the file's others refuse
        load_params(overrides={"geometry.b": 0.1})
    assert "with --set geometry.b=0.1: geometry: b = 0.1 m must be smaller than L" in str(err.value), str(err.value)


def test_unknown_keys_are_refused(params, tmp_path):
    data = tomllib.loads(params.to_toml())
    data["springs"]["k_middle"] = [1.0, 2.0, 3.0]
    with pytest.raises(ParameterError, match=r"unknown field `k_middle` - at|springs.*k_middle|k_middle"):
        params_from_dict(data)
    with pytest.raises(ParameterError, match=r"override 'springs\.k_middle': unknown key"):
        load_params(overrides={"springs.k_middle": 1.0})
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry\nL = 1")
    with pytest.raises(ParameterError, match="not a valid TOML file"):
        load_params(bad)
    with pytest.raises(ParameterError, match="cannot read parameter file"):
        load_params(tmp_path / "missing.toml")
    # audit of 2026-11-26: these escaped as UnicodeDecodeError / RecursionError (500 on the console)
    latin = tmp_path / "latin.toml"
    latin.write_bytes(params.to_toml().replace('name = "', 'name = "caf\xe9 ').encode("latin-1"))
    with pytest.raises(ParameterError, match=r"latin\.toml: not UTF-8 text"):
        load_params(latin)
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 50_000 + "]" * 50_000 + "\n")
    with pytest.raises(ParameterError, match=r"deep\.toml: .*nested too deeply"):
        load_params(deep)


def test_cli_model_prints_the_model_at_one_configuration(model, xneck):
    from twin.model import cables

    run = xneck("model", "--alpha", "40", "-30", "20", "--json")
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    np.testing.assert_allclose(out["Z_m_per_rad"], cables.Z(model, np.radians([40, -30, 20])), rtol=1e-12)
    # l_c − l_c0, named for what it holds (not a cable length)
    np.testing.assert_allclose(out["delta_l_c_m"], cables.l_c(model, np.radians([40, -30, 20])) - model.l_c0, rtol=1e-12)
    assert len(out["spring_left_m"]) == 3 and np.all(np.linalg.eigvalsh(out["M_kg_m2"]) > 0)
    human = xneck("model", "--alpha", "40", "30", "20")
    assert "-30.32" in human.stdout and "Z = −∂l_c/∂α" in human.stdout
    # Audit of 2026-11-29: g, a generalised force conjugate to α in rad, is in N·m (its JSON key
    # g_N_m); N·m/rad is a stiffness's unit (twin.analysis.statics).
    assert "g, springs + gravity (N·m)" in human.stdout and "N·m/rad" not in human.stdout, human.stdout
    assert "g_N_m" in out


def test_cli_model_rejects_bad_input_without_a_traceback(xneck):
    run = xneck("model", "--alpha", "40", "30")
    assert run.returncode == 2 and "needs 3 finite angles" in run.stderr and "Traceback" not in run.stderr
    run = xneck("model", "--alpha", "1", "2", "3", "--set", "geometry.b=0.3")
    assert run.returncode == 2 and "must be smaller than L" in run.stderr and "Traceback" not in run.stderr


def test_to_toml_reads_back_whatever_strings_a_set_holds(params):
    """Audit of 2026-11-27: routing strings are split on any whitespace, so "1d\\n2b" is a valid
    route; to_toml wrote the newline raw, and the TOML a campaign sends its controller service (and
    records in its archive) did not parse. Names with quotes, backslashes and control characters too."""
    data = params.to_dict()
    data["cables"]["routing"] = ["1b", "1d\n2b", "1d\t2d\r3b", "1c\x0c2c\x1f3a"]
    data["name"] = 'a "quoted" \\ name\x00\x7f é'
    odd = params_from_dict(data)
    assert odd.routes == params.routes
    back = params_from_dict(tomllib.loads(odd.to_toml()))
    assert back == odd


def test_an_estimate_past_the_checked_bounds_keeps_the_base_value_and_says_why():
    """An identified λ, k or f_s the estimator accepts (small σ) but a parameter set refuses
    (above): the base value stays, named in the report, and the set loads (before the λ bound an
    identified λ of 1e5 1/m would have made the set fail to load; f_s and k could already)."""
    from types import SimpleNamespace

    import numpy as np

    from twin.identification.estimators import Estimate
    from twin.identification.pipeline import identified_params, make_provenance

    base = load_params()

    def estimate(method, names, values):
        v = np.asarray(values, dtype=float)
        return Estimate(method=method, equations="test", names=tuple(names), values=v, sigma=0.01 * v,
                        relative_sigma=np.full(len(v), 0.01), condition_number=1.0, residual_norm=0.0,
                        n_rows=100, n_samples=100)

    lam = [100.0, 1e5, 50.0, 120.0]
    est = {"friction": estimate("friction", [f"f_s({j})" for j in range(1, 5)], [15.0, 16.0, 300.0, 17.0]),
           "variable": estimate("variable", [f"{s}({j})" for s in ("k", "lambda", "c_a") for j in range(1, 5)],
                                [5000.0, 2e7, 6000.0, 2000.0, *lam, *[3000.0] * 4])}
    new, report, _ = identified_params(base, est, make_provenance("t", SimpleNamespace(cutoff_hz=1.0, rate_hz=31.25)))  # type: ignore[arg-type]
    assert list(new.friction.f_s) == [15.0, 16.0, base.friction.f_s[2], 17.0]
    assert list(new.cables.variable.k) == [5000.0, base.cables.variable.k[1], 6000.0, 2000.0]
    # λ(2) against the k the set keeps for cable 2 (its estimate was refused)
    assert list(new.cables.variable.lam) == [100.0, base.cables.variable.lam[1], 50.0, 120.0]
    assert "peak force" in report.kept_base["friction.f_s(3)"][2]
    assert "N/m the twin" in report.kept_base["cables.variable.k(2)"][2]
    assert "stiffen past" in report.kept_base["cables.variable.lambda(2)"][2]
