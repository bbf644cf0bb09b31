"""The controller's campaign service as a pure state machine (issue 12): its life cycle, holds and
request handling, against the twin's simulator in the same process, without any bus."""

from __future__ import annotations

import numpy as np
import pytest

from bridge import bus
from controller.laws import LawConfig, hold_forces
from controller.service import CampaignService
from controller.trajectory import Trajectory
from twin.sim.simulator import Twin, TwinConfig

NOD = Trajectory.from_degrees([[0, 0, 0], [10, 5, 0]], 1.0, 0.2, name="nod")


def _request(cid="c-1", action="start", trajectory_json=NOD.to_json(), **kw) -> bus.CampaignRequest:
    return bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id=cid, action=action, trajectory_json=trajectory_json, **kw)


class Loop:
    """The service closed on the simulator, one state per 2 ms: what the bus shell does."""

    def __init__(self, params, service=True):
        self.twin = Twin(params, TwinConfig(camera=False, seed=1))
        self.svc = CampaignService(params, LawConfig(law=2), service=service, settle_s=0.2)
        self.tick = self.twin.tick(np.zeros(params.n_cables))
        self.svc.initialise(self.tick.theta_meas)
        self.events: list = []
        self.outputs: list = []

    @property
    def stamp_s(self) -> float:
        return self.tick.t_s

    def run(self, seconds: float, theta=None) -> None:
        for _ in range(round(seconds * 500)):
            out = self.svc.control(self.tick.theta_meas if theta is None else theta, self.stamp_s)
            self.outputs.append(out)
            if out.law_ran:
                self.svc.advance(self.stamp_s)
            self.events += self.svc.drain_events()
            self.tick = self.twin.tick(out.force_N)


@pytest.fixture
def loop(params):
    return Loop(params)


def test_idle_service_holds_the_neck_where_it_started(loop):
    loop.run(0.5)
    assert loop.svc.phase == "idle" and not loop.events
    assert np.degrees(np.abs(loop.tick.alpha)).max() < 1.0
    assert all(o.law_ran and np.all(np.isfinite(o.force_N)) for o in loop.outputs)


def test_a_requested_campaign_runs_to_finished_and_then_holds_its_last_waypoint(loop):
    loop.svc.handle(_request(), loop.stamp_s)
    assert loop.svc.phase == "running"
    loop.run(NOD.duration_s + 0.2 + 0.05)
    kinds = [e.event for e in loop.events]
    assert kinds[0] == "started" and kinds[-1] == "finished" and "progress" in kinds
    assert all(e.campaign_id == "c-1" for e in loop.events)
    assert loop.svc.phase == "finished" and not loop.svc.running
    np.testing.assert_allclose(loop.svc.hold_target, NOD.waypoints_rad[-1])
    assert np.degrees(np.abs(loop.tick.alpha - NOD.waypoints_rad[-1])).max() < 2.0  # law 2 with rigid cables in α̂


def test_stop_aborts_the_running_campaign_and_a_second_start_is_refused(loop):
    loop.svc.handle(_request("c-1"), loop.stamp_s)
    loop.run(0.1)
    loop.svc.handle(_request("c-2"), loop.stamp_s)
    loop.svc.handle(_request("c-other", action="stop"), loop.stamp_s)  # not the running one: ignored
    loop.svc.handle(_request("c-1", action="stop"), loop.stamp_s)
    events = loop.events + loop.svc.drain_events()
    refused = [e for e in events if e.campaign_id == "c-2"]
    assert [e.event for e in refused] == ["aborted"] and "running campaign c-1" in refused[0].message
    stopped = [e for e in events if e.campaign_id == "c-1"][-1]
    assert stopped.event == "aborted" and stopped.message == "stopped by the user" and 0 < stopped.progress < 1
    assert loop.svc.phase == "aborted" and not loop.svc.running


def test_a_trajectory_beyond_the_limits_is_refused_with_the_reason(loop):
    reach = Trajectory.from_degrees([[0, 0, 0], [30, 70, 0]], 3.0)
    loop.svc.handle(_request("c-far", trajectory_json=reach.to_json()), loop.stamp_s)
    (ev,) = loop.svc.drain_events()
    assert ev.event == "aborted" and ev.campaign_id == "c-far" and "waypoint 1" in ev.message
    assert loop.svc.phase == "idle"


def test_a_diverging_estimate_latches_a_hold_at_the_last_sane_estimate(loop, params):
    loop.svc.handle(_request(), loop.stamp_s)
    loop.run(0.3)
    sane = loop.svc.last_sane.copy()
    loop.run(0.01, theta=np.array([1e3, -1e3, 0.0, 0.0]))  # encoders gone mad
    aborted = [e for e in loop.events if e.event == "aborted"]
    assert len(aborted) == 1 and "diverging estimate" in aborted[0].message
    assert loop.svc.latched and loop.svc.hold_reason.startswith("diverging")
    last = loop.outputs[-1]
    assert not last.law_ran
    np.testing.assert_allclose(last.force_N, hold_forces(params, sane))
    # A new campaign lifts the latch.
    loop.svc.handle(_request("c-2", trajectory_json=Trajectory.from_degrees([[0, 0, 0]], [], 0.1).to_json()),
                    loop.stamp_s)
    assert not loop.svc.latched and loop.svc.phase == "running"


def test_a_headless_campaign_ends_aborted_on_divergence(params):
    loop = Loop(params, service=False)
    loop.svc.begin(NOD, loop.stamp_s)
    loop.run(0.1)
    loop.run(0.004, theta=np.array([1e3, -1e3, 0.0, 0.0]))
    assert loop.svc.outcome == "aborted" and loop.events[-1].event == "aborted"
