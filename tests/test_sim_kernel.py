"""The twin's period as one compiled call (issue 21: twin >= 150x real time): the same numbers as
plain Python, the solver against LAPACK, and Ticks that own their arrays."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twin.sim.integrator import _cholesky_solve
from twin.sim.simulator import Twin, TwinConfig

ROOT = Path(__file__).resolve().parents[1]

RUN_SCRIPT = """
import json
import numpy as np
from twin.model import compiled
from twin.sim.simulator import Twin, TwinConfig
out = {"numba": compiled.numba_enabled()}
for truth in ("model", "robot"):
    twin = Twin(config=TwinConfig(truth=truth, seed=3))
    ticks = [twin.tick(np.array([30.0, 25.0, 20.0, 28.0]) * (1 + 0.5 * np.sin(k / 5))) for k in range(40)]
    out[truth] = [np.concatenate([t.alpha, t.theta, t.alpha_dot, t.theta_dot, t.tension, t.elongation,
                                  t.theta_meas, t.slack]).tolist() for t in ticks]
print(json.dumps(out))
"""


def _run(no_numba: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XNECK_NO_NUMBA"}
    if no_numba:
        env["XNECK_NO_NUMBA"] = "1"
    run = subprocess.run([sys.executable, "-c", RUN_SCRIPT], capture_output=True, text=True, timeout=300, cwd=ROOT,
                         env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout)


def test_the_twin_runs_as_plain_python_with_the_compiled_numbers():
    """Issue 20: one implementation, two ways to run it. The period kernel (actuation, stiction,
    creep, encoders through the backlash: the robot truth) is the same code without numba."""
    plain, fast = _run(no_numba=True), _run(no_numba=False)
    assert plain["numba"] is False and fast["numba"] is True
    for truth in ("model", "robot"):
        np.testing.assert_allclose(np.array(plain[truth]), np.array(fast[truth]), rtol=0, atol=1e-9)


def test_cholesky_solve_equals_lapack_and_refuses_a_matrix_that_is_not_positive_definite():
    rng = np.random.default_rng(21)
    G = rng.normal(size=(7, 7))
    A = G @ G.T + np.diag(rng.uniform(1e-5, 1.0, 7))
    B = rng.normal(size=(7, 5))
    X = B.copy()
    assert _cholesky_solve(A, np.empty((7, 7)), X, 5)
    np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-9, atol=1e-12)
    X = B.copy()
    assert _cholesky_solve(A, np.empty((7, 7)), X, 2)
    np.testing.assert_array_equal(X[:, 2:], B[:, 2:])  # only the columns asked for
    indefinite = A.copy()
    indefinite[3, 3] = -1.0
    assert not _cholesky_solve(indefinite, np.empty((7, 7)), B.copy(), 1)
    assert not _cholesky_solve(np.full((7, 7), np.nan), np.empty((7, 7)), B.copy(), 1)


def test_ticks_own_their_arrays_and_the_state_array_stays_the_integrators():
    """The kernel writes into arrays it keeps: a Tick must not change with the next period, and
    writing into a Tick must not move the robot. ``state`` is written in place (calibration
    replays re-start the motors that way), never replaced."""
    twin = Twin(config=TwinConfig(camera=False))
    f = np.array([30.0, 25.0, 20.0, 28.0])
    first = twin.tick(f)
    kept = {name: np.copy(getattr(first, name)) for name in
            ("alpha", "alpha_dot", "theta", "theta_dot", "tension", "elongation", "theta_meas", "slack")}
    state = twin.state.copy()
    first.alpha[:] = 1.0
    first.theta_meas[:] = 1.0
    np.testing.assert_array_equal(twin.state, state)
    first.alpha[:], first.theta_meas[:] = kept["alpha"], kept["theta_meas"]
    second = twin.tick(2 * f)
    assert not np.array_equal(second.alpha, first.alpha)
    for name, value in kept.items():
        np.testing.assert_array_equal(getattr(first, name), value, err_msg=name)
    with pytest.raises(AttributeError):
        twin.state = np.zeros_like(state)  # pyright: ignore[reportAttributeAccessIssue]
    n, nc = twin.model.n_joints, twin.model.n_cables
    twin.state[n : n + nc] += 0.01  # written in place: the next period starts from it
    moved = twin.tick(2 * f)
    reference = Twin(config=TwinConfig(camera=False))
    reference.tick(f)
    reference.tick(2 * f)
    assert not np.array_equal(moved.theta, reference.tick(2 * f).theta)



def test_the_carved_scratch_has_the_models_scratch_shapes_and_no_overlap():
    """integrator.carve lays the twin's scratch out in one array: the model's part must have the
    shapes twin.model.dynamics.scratch_buffers gives, and no two views may share memory."""
    from twin.model.dynamics import scratch_buffers
    from twin.sim.integrator import carve, scratch

    twin = Twin(config=TwinConfig(camera=False))
    n, nc = twin.model.n_joints, twin.model.n_cables
    pool = scratch(n, nc)
    work, scr, used = carve(pool, n, nc)
    assert used == pool.size and not pool.any()
    assert [a.shape for a in work] == [a.shape for a in scratch_buffers(twin.model)]
    views = [*work, *scr]
    for k, a in enumerate(views):
        assert np.shares_memory(a, pool)
        for b in views[k + 1 :]:
            assert not np.shares_memory(a, b)
    assert sum(a.size for a in views) == pool.size
