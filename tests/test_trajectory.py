"""Desired trajectories (controller/trajectory.py): cycloids, the paper's trajectories, user files,
and every rejection path of validate()."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from controller.trajectory import (
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    control_test_trajectory,
    cycloid,
    identification_trajectory,
    load_trajectory,
    recorded_excitation,
    trajectory_by_name,
    trajectory_json_schema,
    validate,
)

LIMITS = TrajectoryLimits()


def user(**kw) -> Trajectory:
    spec = {"name": "u", "waypoints_deg": [[0, 0, 0], [20, 10, 0], [0, -10, 5]], "durations_s": [2.0, 1.5], "dwell_s": 0.5}
    spec.update(kw)
    return load_trajectory(spec)


# -- cycloid ------------------------------------------------------------------------------------


def test_cycloid_boundary_conditions():
    s, ds, dds = cycloid(np.array([0.0, 1.0, -0.3, 1.7]))
    np.testing.assert_array_equal(s, [0.0, 1.0, 0.0, 1.0])
    np.testing.assert_array_equal(ds, 0.0)
    np.testing.assert_array_equal(dds, 0.0)
    s, ds, dds = cycloid(0.5)
    assert s == pytest.approx(0.5) and ds == pytest.approx(2.0) and dds == pytest.approx(0.0, abs=1e-12)
    assert cycloid(0.25)[2] == pytest.approx(2 * math.pi)


def test_cycloid_derivatives_match_finite_differences():
    tau = np.linspace(0.01, 0.99, 200)
    h = 1e-6
    s, ds, dds = cycloid(tau)
    np.testing.assert_allclose(ds, (cycloid(tau + h)[0] - cycloid(tau - h)[0]) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(dds, (cycloid(tau + h)[1] - cycloid(tau - h)[1]) / (2 * h), atol=1e-6)
    assert np.all(np.diff(s) > 0)  # monotonic: waypoints within limits ⇒ whole path within limits


# -- sampling -----------------------------------------------------------------------------------


@pytest.mark.parametrize("traj", [user(), control_test_trajectory(), identification_trajectory()], ids=lambda t: t.name)
def test_sample_derivatives_match_numerical_differentiation(traj):
    t = np.linspace(-0.5, traj.duration_s + 0.5, 4001)
    h = 1e-6  # small: at waypoints the jerk jumps, and the central-difference error there is ∝ h
    alpha, alpha_dot, alpha_ddot = traj.sample(t)
    assert alpha.shape == alpha_dot.shape == alpha_ddot.shape == (t.size, traj.n_joints)
    np.testing.assert_allclose(alpha_dot, (traj.sample(t + h).alpha - traj.sample(t - h).alpha) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(
        alpha_ddot, (traj.sample(t + h).alpha_dot - traj.sample(t - h).alpha_dot) / (2 * h), atol=1e-5
    )


def test_continuity_and_rest_at_waypoints():
    traj = user(dwell_s=0.0)  # no hold: moves meet head to tail
    eps = 1e-9
    for k, tk in enumerate(traj.waypoint_times()):
        for side in (tk - eps, tk, tk + eps):
            a, ad, add = traj.sample(side)
            np.testing.assert_allclose(a, traj.waypoints_rad[k], atol=1e-12)
            np.testing.assert_allclose(ad, 0.0, atol=1e-7)
            np.testing.assert_allclose(add, 0.0, atol=1e-6)
    # holds return the waypoint bit-exactly, before the start and after the end too
    traj = user()
    for k, (arrive, leave) in enumerate(zip(traj.waypoint_times(), traj.waypoint_times() + traj.dwell_s)):
        a = traj.sample(np.linspace(arrive, leave, 5)).alpha
        assert np.array_equal(a, np.broadcast_to(traj.waypoints_rad[k], a.shape))
    assert np.array_equal(traj.sample(-3.0).alpha, traj.waypoints_rad[0])
    assert np.array_equal(traj.sample(traj.duration_s + 10).alpha, traj.waypoints_rad[-1])


def test_timeline_and_shapes():
    traj = user()
    assert traj.duration_s == pytest.approx(3 * 0.5 + 2.0 + 1.5)
    np.testing.assert_allclose(traj.waypoint_times(), [0.0, 2.5, 4.5])
    np.testing.assert_allclose(traj.segment_times(), [[0.5, 2.5], [3.0, 4.5]])
    assert traj.sample(1.0).alpha.shape == (3,)
    assert traj.sample(np.zeros((2, 4))).alpha.shape == (2, 4, 3)
    assert traj.describe_time(1.0) == "segment 0 (waypoint 0 → 1)"
    assert traj.describe_time(2.7) == "hold at waypoint 1"
    with pytest.raises(ValueError):
        traj.waypoints_rad[0, 0] = 1.0  # immutable
    single = Trajectory(np.zeros((1, 2)), [], 1.0)  # pyright: ignore[reportArgumentType] - plain values are converted
    assert single.duration_s == 1.0 and single.sample([0.0, 5.0]).alpha.shape == (2, 2)
    one_joint = Trajectory.from_degrees([[0], [30]], 1.0)
    assert one_joint.sample(1.0).alpha == pytest.approx([math.radians(30)])


# -- the paper's trajectories -------------------------------------------------------------------


def test_identification_trajectory_visits_paper_configurations():
    traj = identification_trajectory()
    assert traj.n_segments == 24 and traj.n_joints == 3
    w = np.rad2deg(traj.waypoints_rad)
    amps = [(40, 30, 20), (-40, 30, 20), (40, -30, 20), (40, 30, -20)]
    for seq, a in enumerate(amps):
        a = np.array(a, float)
        expected = [np.zeros(3), a, -a, np.zeros(3), -a, a, np.zeros(3)]
        np.testing.assert_allclose(w[6 * seq : 6 * seq + 7], expected, atol=1e-12)
    validate(traj, LIMITS, 3)
    assert traj.duration_s == pytest.approx(25 * 1.0 + 24 * 3.0)
    assert identification_trajectory(motion_s=2.0, dwell_s=0.0).duration_s == pytest.approx(48.0)


def test_control_test_matches_fig10_timings():
    traj = control_test_trajectory()
    t = np.array([0.0, 4.0, 7.0, 10.0])
    np.testing.assert_allclose(
        np.rad2deg(traj.sample(t).alpha), [[0, 0, 0], [50, 50, 50], [0, 0, 0], [-30, -40, -50]], atol=1e-12
    )
    np.testing.assert_allclose(traj.sample(t).alpha_dot, 0.0, atol=1e-12)  # stop phases
    np.testing.assert_allclose(traj.segment_times(), [[1, 3], [4, 6], [7, 9], [10, 12]])
    assert traj.duration_s == pytest.approx(13.0)
    validate(traj, LIMITS, 3)
    # The no-stop variant arrives exactly at 4, 7 and 10 s.
    alt = control_test_trajectory(motion_s=3.0, dwell_s=0.0, rest_s=1.0)
    np.testing.assert_allclose(alt.waypoint_times()[1:4], [4.0, 7.0, 10.0])


def test_trajectory_by_name():
    assert trajectory_by_name("identification").name == "identification"
    assert trajectory_by_name("control-test", motion_s=3.0).durations_s[0] == 3.0
    with pytest.raises(TrajectoryError, match="unknown trajectory 'spiral'; known: identification, control_test"):
        trajectory_by_name("spiral")


# -- files and serialisation --------------------------------------------------------------------


def test_json_and_toml_round_trip(tmp_path):
    traj = identification_trajectory(motion_s=2.5, dwell_s=0.25)
    path = tmp_path / "ident.json"
    path.write_text(traj.to_json())
    back = load_trajectory(path)
    assert back.to_dict() == traj.to_dict()
    np.testing.assert_allclose(back.waypoints_rad, traj.waypoints_rad, rtol=0, atol=1e-12)

    toml = tmp_path / "nod.toml"
    toml.write_text('name = "nod"\nwaypoints_deg = [[0, 0, 0], [20, 10, 0], [0, 0, 0]]\ndurations_s = 2\ndwell_s = [1, 0, 0.5]\n')
    nod = load_trajectory(toml)
    assert nod.name == "nod" and nod.duration_s == pytest.approx(5.5)
    np.testing.assert_allclose(np.rad2deg(nod.waypoints_rad[1]), [20, 10, 0])
    assert load_trajectory(json.loads(json.dumps(nod.to_dict()))).to_dict() == nod.to_dict()
    assert Trajectory.from_dict(nod.to_dict()).to_dict() == nod.to_dict()
    assert trajectory_json_schema()["$defs"]["TrajectoryFile"]["required"] == ["waypoints_deg"]


@pytest.mark.parametrize(
    ("content", "suffix", "message"),
    [
        ('{"waypoints_deg": [[0, 0, 0]], "duration_s": 1}', ".json", "unknown field `duration_s`"),
        ('{"waypoints_deg": "up"}', ".json", r"\$.waypoints_deg"),
        ("{not json", ".json", "malformed"),
        ("waypoints_deg = [[0, 0, 0]", ".toml", "nod.toml"),
        ("", ".yaml", "unknown trajectory file type '.yaml'"),
    ],
)
def test_bad_files_are_rejected_with_context(tmp_path, content, suffix, message):
    path = tmp_path / f"nod{suffix}"
    path.write_text(content)
    with pytest.raises(TrajectoryError, match=message):
        load_trajectory(path)


def test_a_misspelt_built_in_name_is_said_to_be_neither_a_name_nor_a_file(tmp_path):
    """``--trajectory contol_test`` said "unknown trajectory file type ''" (session 47)."""
    with pytest.raises(TrajectoryError, match=r"contol_test: no built-in trajectory of that name \(identification or "
                                              r"control_test\) and no such file"):
        load_trajectory(tmp_path / "contol_test")
    (tmp_path / "waypoints").write_text("")  # a file without a suffix: its type is what is wrong
    with pytest.raises(TrajectoryError, match="unknown trajectory file type ''"):
        load_trajectory(tmp_path / "waypoints")


# -- rejection paths ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"waypoints_deg": []}, "empty trajectory"),
        ({"waypoints_deg": [[0, 0, 0], [10, 0]]}, "waypoint 1 has 2 joints, waypoint 0 has 3"),
        ({"waypoints_deg": [[0, 0, 0], [10, float("nan"), 0]], "durations_s": 1}, r"waypoint 1 has a non-finite value"),
        ({"waypoints_deg": [[0, 0, 0], [10, 0, 0], [0, 0, 0]], "durations_s": [1, 0]}, r"segment 1 \(waypoint 1 → 2\) has a non-positive"),
        ({"waypoints_deg": [[0, 0, 0], [10, 0, 0]], "durations_s": -1}, r"segment 0 .* non-positive"),
        ({"waypoints_deg": [[0, 0, 0], [10, 0, 0]], "durations_s": [1, 1]}, "expected 1 segment duration"),
        ({"waypoints_deg": [[0, 0, 0], [10, 0, 0]]}, "expected 1 segment duration .* got 0"),
        ({"waypoints_deg": [[0, 0, 0], [10, 0, 0]], "durations_s": 1, "dwell_s": [0, -1]}, "waypoint 1 has a negative"),
        # finite parts whose sum overflows (audit of 2026-11-27: a 500 on POST /api/trajectories/validate)
        ({"waypoints_deg": [[0, 0, 0], [0, 0, 0], [0, 0, 0]], "durations_s": [1e308, 1e308]}, "total duration .* not finite"),
        ({"waypoints_deg": [[0, 0, 0], [0, 0, 0]], "durations_s": 1e308, "dwell_s": 1e308}, "total duration .* not finite"),
        # a zero-length move of 1e-200 s was refused as "needs nan N on cable 1" (audit of 2026-11-27)
        ({"waypoints_deg": [[0, 0, 0], [0, 0, 0], [10, 0, 0]], "durations_s": [1e-200, 2]},
         r"segment 0 \(waypoint 0 → 1\) lasts 1e-200 s, under the shortest move 1 ms"),
    ],
)
def test_malformed_trajectories_name_waypoint_or_segment(spec, message):
    with pytest.raises(TrajectoryError, match=message):
        load_trajectory(spec)


def test_rejects_wrong_number_of_joints():
    with pytest.raises(TrajectoryError, match="wrong number of joints: waypoints have 3, the robot has 2"):
        validate(user(), LIMITS, 2)


def test_rejects_waypoint_out_of_joint_limits():
    traj = user(waypoints_deg=[[0, 0, 0], [20, 10, 0], [0, -65, 5]])
    with pytest.raises(TrajectoryError, match=r"waypoint 2 \(\[0, -65, 5\]°\) is out of the joint limits: α2 = -65° exceeds ±60°"):
        validate(traj, LIMITS, 3)
    validate(user(waypoints_deg=[[0, 0, 0], [60, -60, 0], [0, 0, 0]], durations_s=3.0), LIMITS, 3)  # edge passes
    slow = user(waypoints_deg=[[0, 0, 0], [20, 10, 0], [0, -65, 5]], durations_s=3.0)
    validate(slow, TrajectoryLimits.from_degrees(alpha_max_deg=(60.0, 70.0, 60.0)), 3)  # per-joint limits


def test_rejects_too_fast_and_too_much_acceleration():
    fast = user(waypoints_deg=[[0, 0, 0], [0, 0, 50], [0, 0, 0]], durations_s=[3.0, 1.0])
    # segment 1: 50° in 1 s peaks at 100°/s > 85.94°/s
    with pytest.raises(TrajectoryError, match=r"segment 1 \(waypoint 1 → 2, 1 s\) is too fast: α3 peaks at 100°/s > 85.94°/s; needs at least 1.16 s"):
        validate(fast, LIMITS, 3)
    jerky = TrajectoryLimits(alpha_dot_max_rad_s=10.0, alpha_ddot_max_rad_s2=1.0)
    with pytest.raises(TrajectoryError, match=r"segment 1 \(waypoint 1 → 2, 1 s\) has too much acceleration: α3 peaks at 314.2°/s² > 57.3°/s²; needs at least 2.34 s"):
        validate(fast, jerky, 3)
    with pytest.raises(TrajectoryError, match=r"limit alpha_dot_max_rad_s has 2 values for 3 joints"):
        validate(fast, TrajectoryLimits(alpha_dot_max_rad_s=(1.0, 1.0)), 3)
    with pytest.raises(ValueError, match="alpha_max_rad must be positive"):
        TrajectoryLimits(alpha_max_rad=-1.0)


def test_peak_rates_are_exact():
    traj = user(dwell_s=0.0)
    t = np.linspace(0.0, traj.duration_s, 200001)
    s = traj.sample(t)
    np.testing.assert_allclose(np.abs(s.alpha_dot).max(axis=0), traj.segment_peak_velocity().max(axis=0), rtol=1e-6)
    np.testing.assert_allclose(np.abs(s.alpha_ddot).max(axis=0), traj.segment_peak_acceleration().max(axis=0), rtol=1e-6)


def test_force_check_hook():
    traj = control_test_trajectory()
    calls = []

    def f_ok(alpha, alpha_dot, alpha_ddot, pretension):
        calls.append(alpha.shape)
        return np.ones(alpha.shape[0], bool), ""

    validate(traj, LIMITS, 3, force_check=f_ok)
    assert calls and calls[0][0] >= 1300 and calls[0][1] == 3  # 10 ms over 13 s

    def f_max(alpha, alpha_dot, alpha_ddot, pretension):  # pretend large α3 needs f > f_max
        return alpha[:, 2] > math.radians(-45.0), "f_4 = 120 N > f_max = 100 N"

    with pytest.raises(TrajectoryError, match=r"forces out of bounds in segment 2 \(waypoint 2 → 3\) at t = 8\.\d+ s .*f_4 = 120 N > f_max"):
        validate(traj, LIMITS, 3, force_check=f_max)

    def f_hold(alpha, alpha_dot, alpha_ddot, pretension):
        return np.linalg.norm(alpha_dot, axis=1) > 0, "f_min violated at rest"

    with pytest.raises(TrajectoryError, match=r"hold at waypoint 0 at t = 0\.000 s"):
        validate(traj, LIMITS, 3, force_check=f_hold)

    with pytest.raises(ValueError, match="force_check must return a bool array"):
        validate(traj, LIMITS, 3, force_check=lambda a, ad, add, p: (np.ones(3, bool), ""))

    never = lambda a, ad, add, p: pytest.fail("force_check must not run on a trajectory that fails limits")  # noqa: E731
    with pytest.raises(TrajectoryError, match="out of the joint limits"):
        validate(user(waypoints_deg=[[0, 0, 0], [70, 0, 0], [0, 0, 0]]), LIMITS, 3, force_check=never)


def test_a_repeated_trajectory_runs_its_passes_back_to_back():
    from controller.trajectory import identification_trajectory, repeated

    one = identification_trajectory()
    four = repeated(one, 4)
    assert four.duration_s == pytest.approx(4 * one.duration_s - 3 * one.dwell_s[0])
    assert four.n_waypoints == 4 * one.n_waypoints - 3 and four.name == "identification-x4"
    t = np.linspace(0.0, one.duration_s - one.dwell_s[-1], 500)
    second = t + one.duration_s - one.dwell_s[-1]  # the second pass starts where the first one's final rest would
    np.testing.assert_allclose(four.sample(second).alpha, one.sample(t).alpha, atol=1e-12)
    validate(four, LIMITS, 3)
    assert repeated(one, 1).duration_s == one.duration_s
    with pytest.raises(TrajectoryError, match="cannot be repeated"):
        repeated(Trajectory.from_degrees([[0, 0, 0], [10, 0, 0]], 1.0), 2)
    with pytest.raises(TrajectoryError, match="at least once"):
        repeated(one, 0)


def test_a_brake_comes_to_rest_from_speed_without_a_step_and_within_the_joint_limits():
    from controller.trajectory import BRAKE_ACCELERATION_MAX_RAD_S2, brake_at, brake_duration_s

    a0, v0 = np.array([0.3, -0.2, 0.0]), np.array([0.6, -0.3, 0.0])
    duration = brake_duration_s(a0, v0, math.radians(60.0))
    t = np.linspace(0.0, duration, 2001)
    samples = [brake_at(a0, v0, duration, float(x)) for x in t]
    a = np.array([s[0] for s in samples])
    v = np.array([s[1] for s in samples])
    acc = np.array([s[2] for s in samples])
    np.testing.assert_allclose(a[0], a0)
    np.testing.assert_allclose(v[0], v0)  # no step in α^d or α̇^d at the stop
    np.testing.assert_allclose(acc[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(v[-1], 0.0, atol=1e-12)
    np.testing.assert_allclose(a[-1], a0 + v0 * duration / 2.0)
    np.testing.assert_allclose(np.gradient(a, t, axis=0), v, atol=1e-3)  # α̇ is α's derivative
    assert np.abs(acc).max() <= BRAKE_ACCELERATION_MAX_RAD_S2 * (1 + 1e-9)
    # at full speed towards a joint limit, the stop is firmer but ends within it
    near = np.array([math.radians(59.0), 0.0, 0.0])
    fast = np.array([1.5, 0.0, 0.0])
    short = brake_duration_s(near, fast, math.radians(60.0))
    end = brake_at(near, fast, short, short)[0]
    assert end[0] <= math.radians(60.0) + 1e-12 and short < brake_duration_s(np.zeros(3), fast, math.radians(60.0))
    assert brake_duration_s(a0, np.zeros(3), math.radians(60.0)) > 0  # at rest: a short, smooth stop


@pytest.mark.parametrize("acc0", [[2.9, -1.9, 1.0], [-2.9, 1.9, -1.0]], ids=["accelerating", "decelerating"])
def test_a_brake_lets_go_of_the_acceleration_it_starts_with_without_a_step(acc0):
    """Session 45: a stop at a trajectory's peak acceleration (2.9 rad/s²) started its brake at
    α̈ = 0 and stepped the law's feed-forward 2.35 N in one tick. The brake starts at α̈₀ and lets
    go of it at most ``BRAKE_JERK_MAX_RAD_S3``, comes to rest where it says, within the bound on
    α̈ and within the joint limits."""
    from controller.trajectory import (
        BRAKE_ACCELERATION_MAX_RAD_S2,
        BRAKE_JERK_MAX_RAD_S3,
        brake_at,
        brake_duration_s,
        brake_path,
        release_duration_s,
    )

    a0, v0, acc = np.radians([20.0, -13.0, 7.0]), np.array([0.5, -0.33, 0.17]), np.array(acc0)
    duration = brake_duration_s(a0, v0, math.radians(60.0), acc)
    end_s = max(duration, release_duration_s(acc))
    t = np.linspace(0.0, end_s + 0.1, 4001)
    samples = [brake_at(a0, v0, duration, float(x), acc) for x in t]
    a, v, dd = (np.array([s[k] for s in samples]) for k in range(3))
    path = brake_path(a0, v0, duration, t, acc)
    for k in range(3):
        np.testing.assert_allclose(path[k], [a, v, dd][k], atol=1e-12)  # the checked path is the braked one
    np.testing.assert_allclose(a[0], a0)
    np.testing.assert_allclose(v[0], v0)
    np.testing.assert_allclose(dd[0], acc)  # no step in α̈^d either
    np.testing.assert_allclose(v[t >= end_s], 0.0, atol=1e-12)
    np.testing.assert_allclose(dd[t >= end_s], 0.0, atol=1e-12)
    np.testing.assert_allclose(a[-1], a0 + v0 * duration / 2.0)  # the release leaves no travel
    np.testing.assert_allclose(np.gradient(a, t, axis=0), v, atol=2e-3)
    np.testing.assert_allclose(np.gradient(v, t, axis=0), dd, atol=2e-2)
    assert np.abs(dd).max() <= BRAKE_ACCELERATION_MAX_RAD_S2 * (1 + 1e-6)
    # let go of smoothly: per 2 ms tick, α̈^d changes by what the jerk bound and the cycloid allow
    per_tick = np.abs(np.diff([brake_at(a0, v0, duration, k * 0.002, acc)[2] for k in range(400)], axis=0)).max()
    assert per_tick <= (BRAKE_JERK_MAX_RAD_S3 + 2 * math.pi * 2 * np.abs(v0).max() / duration**2) * 0.002
    # accelerating towards a joint limit: shorter, and the path (not only its end) within it
    near, out = np.array([math.radians(59.0), 0.0, 0.0]), np.array([0.3, 0.0, 0.0])
    short = brake_duration_s(near, out, math.radians(60.0), np.array([3.0, 0.0, 0.0]))
    stretch = brake_path(near, out, short, np.linspace(0.0, 0.5, 501), np.array([3.0, 0.0, 0.0]))[0]
    assert stretch[:, 0].max() <= math.radians(60.0) + 1e-9
    # Review of session 45: near the limit with α̈ outward, the release (then α̈₀T_r²/12 further)
    # fit no brake; the bisection returned 1 ms and stopped every other joint dead (0.8 rad/s in
    # a tick). The release leaves no travel now: a firmer brake fits, within the limit.
    at, lateral, outward = np.radians([59.7, 0.0, 0.0]), np.array([0.05, 0.8, 0.0]), np.array([3.0, 0.0, 0.0])
    kept = brake_duration_s(at, lateral, math.radians(60.0), outward)
    assert kept >= 0.05
    path = brake_path(at, lateral, kept, np.arange(0.0, 1.0, 0.002), outward)
    assert np.abs(np.diff(path[1], axis=0)).max() < 0.05  # rad/s a tick: no dead stop
    assert path[0][:, 0].max() <= math.radians(60.0) + 1e-9
    # at the limit, α̈ outward: nothing fits (the release's excursion is its own): not a 1 ms stop
    assert brake_duration_s(np.radians([60.0, 0.0, 0.0]), np.zeros(3), math.radians(60.0), outward) >= 0.05


def test_a_recorded_trajectory_beyond_any_campaign_is_no_excitation_not_a_memory_error():
    """Audit of 2026-11-27: ``xneck identify`` samples the archive's ``trajectory`` at the record's
    rate; a dwell of 1e308 s failed with numpy's "Maximum allowed size exceeded", one of 1e6 s with a
    MemoryError traceback (4 GB asked for). Such a trajectory gives no excitation (the cutoff then
    comes from the encoders), as an unreadable one does."""
    from controller.trajectory import recorded_excitation

    t = np.arange(0.0, 2.0, 0.002)
    one_pose = '{"waypoints_deg": [[0, 0, 0]], "durations_s": [], "dwell_s": %s}'
    assert recorded_excitation(one_pose % "1e308", t) is None
    assert recorded_excitation(one_pose % "1e6", t) is None
    assert recorded_excitation(control_test_trajectory().to_json(), np.array([0.0, 1e-12, 2e-12])) is None
    exc = recorded_excitation(control_test_trajectory().to_json(), t)
    assert exc is not None and exc.shape == (int(round(13.0 / 0.002)), 3)


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_a_trajectory_file_nested_too_deeply_is_refused_not_a_traceback(tmp_path, suffix):
    """Audit of 2026-11-28: a .toml file of 100,000 nested arrays raised RecursionError out of
    `xneck controller/campaign/excitation --trajectory` (tomllib recurses per level); .json did not."""
    deep = tmp_path / f"deep{suffix}"
    deep.write_text(("waypoints_deg = " if suffix == ".toml" else '{"waypoints_deg": ')
                    + "[" * 100_000 + "]" * 100_000 + ("\n" if suffix == ".toml" else "}"))
    with pytest.raises(TrajectoryError, match=rf"deep\{suffix}: "):
        load_trajectory(deep)


def test_a_recorded_trajectory_nested_too_deeply_gives_no_excitation():
    """Audit of 2026-11-28: an archive's `trajectory` metadata of 100,000 '[' raised RecursionError
    out of `xneck identify` (and a 500 from the console's parameter-set route)."""
    assert recorded_excitation("[" * 100_000, np.linspace(0.0, 1.0, 50)) is None


def test_a_cached_identified_set_nested_too_deeply_is_identified_again(tmp_path):
    """Audit of 2026-11-28: the console's cache of an identified set, damaged into 100,000 nested
    arrays, raised RecursionError (a 500 on POST /api/campaigns/{id}/parameter-set); a damaged
    cache is 'none kept', and the set is identified again."""
    from server.identified_sets import CACHE_NAME, cached_set

    (tmp_path / CACHE_NAME).write_text("[" * 100_000 + "]" * 100_000)
    assert cached_set(tmp_path) is None


def test_a_cached_identified_set_without_its_warning_is_identified_again(tmp_path):
    """A set kept before sets said why not to trust them (``warning``: α_IP stamped off) would be
    saved without it: identified again, as a warning that is no string."""
    import json

    from server.identified_sets import CACHE_NAME, cached_set

    doc = {"toml": "x = 1", "base_parameter_set": "b", "used": {}, "kept_base": {}, "structure_set": []}
    for bad in (doc, {**doc, "warning": 3}):
        (tmp_path / CACHE_NAME).write_text(json.dumps(bad))
        assert cached_set(tmp_path) is None
    (tmp_path / CACHE_NAME).write_text(json.dumps({**doc, "warning": "late"}))
    assert cached_set(tmp_path) == {**doc, "warning": "late"}


@pytest.mark.parametrize("name, said", [
    ("x" * 65, "65 characters, at most 64"),
    ("nod\u202e", "U+202E (RIGHT-TO-LEFT OVERRIDE) at 3"),
    ("a\x00b", "U+0000"),
    ("a\nb", "U+000A"),
    ("a\u2028b", "U+2028"),
])
def test_a_trajectory_name_is_capped_and_refuses_control_characters(tmp_path, name, said):
    """Input audit: a file's name (the CLI's --trajectory, the bus, the console alike) was neither
    capped like the console's 64 characters nor free of controls and bidi overrides."""
    from controller.trajectory import TrajectoryError, load_trajectory

    path = tmp_path / "t.json"
    path.write_text(json.dumps({"name": name, "waypoints_deg": [[0, 0, 0], [5, 0, 0]], "durations_s": 2.0}))
    with pytest.raises(TrajectoryError, match=re.escape(said)):
        load_trajectory(path)
    assert load_trajectory({"name": "x" * 64 + "", "waypoints_deg": [[0, 0, 0]]}).name == "x" * 64
    assert load_trajectory({"name": "nœud à 3 joints", "waypoints_deg": [[0, 0, 0]]}).name == "nœud à 3 joints"
    # an archive's recorded trajectory still sets the filter cutoff, whatever name an older one holds
    from controller.trajectory import recorded_excitation

    text = json.dumps({"name": name, "waypoints_deg": [[0, 0, 0], [5, 0, 0]], "durations_s": 2.0})
    assert recorded_excitation(text, np.arange(0.0, 2.0, 0.002)).shape == (1000, 3)
