"""Which robot a truth's effects apply to (twin/sim/truth.py, ``robot_params``).

Found 2026-11-27: the twin built its robot from the controller's parameter set, so a campaign run
with an identified set (``--params identified.toml``) simulated a robot with the identified k and λ
and spring rates, and the robot truth's deviations applied on top of them: the identified set then
met a robot made to its own measure, and comparing parameter sets on the twin was circular. The
robot truth now names the prototype's file; a parameter set changes what the controller believes.
"""

from __future__ import annotations

import logging

import msgspec
import numpy as np
import pytest

from server.studies.run import with_joints
from twin.model.params import load_params, params_from_dict
from twin.sim.calibrate import truth_toml
from twin.sim.driver import TwinDriver, TwinDriverConfig
from twin.sim.truth import (
    TruthError,
    believed_differently,
    check_truth,
    load_truth,
    parse_truth,
    robot_base,
    truth_params,
)


def _believed():
    """A parameter set as an identification writes it: other k, λ, spring rates and pulley radius."""
    p = load_params()
    return msgspec.structs.replace(
        p, name="prototype-identified",
        cables=msgspec.structs.replace(p.cables, variable=msgspec.structs.replace(
            p.cables.variable, k=tuple(1.3 * k for k in p.cables.variable.k), lam=tuple(0.7 * v for v in p.cables.variable.lam))),
        springs=msgspec.structs.replace(p.springs, k_left=tuple(1.2 * k for k in p.springs.k_left)),
        geometry=msgspec.structs.replace(p.geometry, r=p.geometry.r + 2e-4))


def test_the_robot_truths_twin_is_the_prototype_whatever_the_controller_believes(caplog):
    proto, believed = load_params(), _believed()
    assert load_truth("robot").robot_params == "prototype"
    with caplog.at_level(logging.WARNING, logger="xneck.bridge.twin"):
        driver = TwinDriver(TwinDriverConfig(truth="robot", camera=False), believed)
    # said out loud, naming what the controller believes otherwise
    warned = [r.getMessage() for r in caplog.records if "believes otherwise" in r.getMessage()]
    assert len(warned) == 1 and "cables.variable.k, cables.variable.lambda, geometry.r, springs.k_left" in warned[0], warned
    driver.configure()
    twin = driver.twin
    assert twin is not None
    expected = truth_params(proto, "robot")  # the prototype with the truth's deviations, once
    assert twin.params == expected
    assert np.allclose(twin.params.cables.variable.k, proto.cables.variable.k)  # Table 2: the known answer
    assert not np.allclose(twin.params.springs.k_left, believed.springs.k_left)
    # before: the believed set with the deviations on top of it
    assert twin.params != truth_params(believed, "robot")
    driver.close()


def test_a_truth_without_robot_params_follows_the_controllers_set():
    believed = _believed()
    driver = TwinDriver(TwinDriverConfig(truth="model", camera=False), believed)
    assert driver.params is believed  # the model truth: the controller's model exactly, by design
    assert believed_differently(load_params(), load_params()) == []
    assert robot_base(load_truth("model"), believed) is believed


def test_a_relative_robot_params_is_read_beside_the_truth_file(tmp_path):
    mine = tmp_path / "mine.toml"
    mine.write_text(load_params(overrides={"springs.l0": [0.05, 0.05, 0.05]}).to_toml())  # a lab's as-built file
    sub = tmp_path / "truths"
    sub.mkdir()
    path = sub / "lab.toml"
    path.write_text('name = "lab"\nrobot_params = "../mine.toml"\n[timing]\nenabled = true\n'
                    'delay_ticks = { value = 1, source = "measurement: test" }\n')
    truth = load_truth(str(path))
    assert truth.robot_params == str(mine.resolve())
    built = robot_base(truth, _believed())
    assert built.to_dict() == load_params(mine).to_dict() and built.springs.l0 == (0.05, 0.05, 0.05)
    # a calibrated truth written from it keeps the robot (xneck twin calibrate's writer)
    again = tmp_path / "again.toml"
    again.write_text(truth_toml(truth))
    assert load_truth(str(again)).robot_params == str(mine.resolve())


def test_a_truth_for_another_robot_or_a_bad_robot_params_is_refused_by_name(tmp_path):
    two = params_from_dict(with_joints(load_params().to_dict(), 2), "two joints")
    with pytest.raises(TruthError, match=r"robot of 3 joints and 4 cables .* one of 2 and 3"):
        check_truth("robot", two)
    with pytest.raises(TruthError, match="robot_params"):
        parse_truth({"name": "x", "robot_params": 3})
    with pytest.raises(TruthError, match="robot_params"):
        parse_truth({"name": "x", "robot_params": "the prototype"})
    missing = tmp_path / "t.toml"
    missing.write_text('name = "t"\nrobot_params = "nowhere.toml"\n')
    with pytest.raises(TruthError, match="robot_params of truth 't'"):
        check_truth(str(missing))
