"""The identification's reader of an archived campaign (twin/identification/record.py) against what
a shared bus puts in an archive (audit of 2026-11-29): the α_IP of two cameras, and single
messages stamped far off the others. Archives written with the recorder's own writer and read back."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from bridge import bus
from bridge.archive import write_campaign
from twin.identification.pipeline import IdentificationError
from twin.identification.record import campaign_data_from_mcap

# Computation only: it runs beside the realtime modules at nice 19 (tests/conftest.py).
pytestmark = pytest.mark.background

N_STATES, N_FRAMES = 3000, 180  # 6 s at 500 Hz and 30 Hz


def _states() -> list[tuple[str, int, bus.MotorState]]:
    return [(bus.MOTOR_STATE, int(k * 2e6) + 1, bus.MotorState(
        seq=k + 1, stamp_s=k * 0.002, theta_rad=[0.01 * math.sin(k / 100)] * 4, force_applied_N=[10.0] * 4,
        drive="active", epoch="e", bridge="b")) for k in range(N_STATES)]


def _frames(source: str = "twin-render", shift_s: float = 0.0, offset_rad: float = 0.0) -> list:
    return [(bus.CAMERA_ALPHA, int((k / 30 + shift_s + 0.05) * 1e9) + 2, bus.CameraAlpha(
        seq=k + 1, stamp_s=k / 30 + shift_s + 0.05, capture_stamp_s=k / 30 + shift_s, source=source,
        alpha_ip_rad=[0.1 * math.sin(k / 10) + offset_rad, 0.2, 0.3])) for k in range(N_FRAMES)]


def _archive(path: Path, *parts: list) -> Path:
    msgs = sorted((m for part in parts for m in part), key=lambda m: m[1])
    return write_campaign(path, msgs, {"campaign_id": path.stem})


def _replace(item, **changes):
    key, log_ns, msg = item
    return key, log_ns, msgspec.structs.replace(msg, **changes)


def test_an_archive_holding_two_cameras_is_refused_naming_them_and_read_with_the_one_chosen(tmp_path) -> None:
    """Two α_IP publishers on the bus were recorded interleaved, and `xneck identify` fitted them as
    one camera, exit 0: k(4) 4464 → 7530 N/m written into the identified set."""
    one = campaign_data_from_mcap(_archive(tmp_path / "one.mcap", _states(), _frames()))
    two = _archive(tmp_path / "two.mcap", _states(), _frames(), _frames("usb:1", 1 / 60, math.radians(3))[:150])
    with pytest.raises(IdentificationError, match=r"α_IP of 2 cameras: 'twin-render' \(180 messages\), 'usb:1' "
                                                  r"\(150 messages\).*--alpha-ip-source"):
        campaign_data_from_mcap(two)
    chosen = campaign_data_from_mcap(two, alpha_ip_source="twin-render")
    np.testing.assert_array_equal(chosen.t_ip_s, one.t_ip_s)
    np.testing.assert_array_equal(chosen.alpha_ip_rad, one.alpha_ip_rad)
    assert len(campaign_data_from_mcap(two, alpha_ip_source="usb:1").t_ip_s) == 150
    with pytest.raises(IdentificationError, match=r"no α_IP of 'usb:0'.*'twin-render' \(180 messages\), 'usb:1'"):
        campaign_data_from_mcap(two, alpha_ip_source="usb:0")


def test_an_archive_of_one_camera_reads_whatever_its_source_is_named(tmp_path) -> None:
    """Archives recorded so far hold one camera; an older publisher named none (``source`` '')."""
    for source in ("", "twin-noise"):
        data = campaign_data_from_mcap(_archive(tmp_path / f"c{source}.mcap", _states(), _frames(source)))
        assert len(data.t_ip_s) == N_FRAMES and data.notes == ()
        assert len(campaign_data_from_mcap(tmp_path / f"c{source}.mcap", alpha_ip_source=source).t_ip_s) == N_FRAMES


@pytest.mark.parametrize("capture_s", [1e9, 1e300, -1e9, 0.0])
def test_one_frame_stamped_far_off_the_others_is_dropped_and_said_not_the_record_refused(tmp_path, capture_s) -> None:
    """One stray α_IP stamped capture 1e9 s, recorded mid-campaign: the reader refused the whole
    record, blaming a clock set back while recording."""
    frames = _frames()
    frames.insert(90, _replace(frames[90], seq=1000, capture_stamp_s=capture_s, stamp_s=max(capture_s, 0.0) + 0.05))
    data = campaign_data_from_mcap(_archive(tmp_path / "c.mcap", _states(), frames))
    clean = campaign_data_from_mcap(_archive(tmp_path / "clean.mcap", _states(), _frames()))
    np.testing.assert_array_equal(data.t_ip_s, clean.t_ip_s)
    assert len(data.notes) == 1 and "1 camera frame(s)" in data.notes[0] and f"{capture_s:.6g}" in data.notes[0], data.notes


def test_a_frame_captured_after_its_publication_in_an_archive_recorded_before_the_check_is_dropped(tmp_path) -> None:
    frames = _frames()
    frames[100] = _replace(frames[100], capture_stamp_s=frames[100][2].stamp_s + 0.2)  # 0.15 s late: no outlier by time
    data = campaign_data_from_mcap(_archive(tmp_path / "c.mcap", _states(), frames))
    assert len(data.t_ip_s) == N_FRAMES - 1
    assert len(data.notes) == 1 and "captured after its publication" in data.notes[0], data.notes


def test_one_motor_state_stamped_far_off_the_others_is_dropped_and_said(tmp_path) -> None:
    states = _states()
    states[1500] = _replace(states[1500], stamp_s=1e9)
    data = campaign_data_from_mcap(_archive(tmp_path / "c.mcap", states, _frames()))
    assert len(data.t_s) == N_STATES - 1 and data.t_s[-1] < 6.0
    assert len(data.notes) == 1 and "1 motor state(s)" in data.notes[0], data.notes


def test_a_clock_set_back_is_still_refused_and_so_are_too_many_strays(tmp_path) -> None:
    """Many frames on another clock are no stray: a camera clock stepped back 10 s halfway."""
    frames = [_replace(f, capture_stamp_s=f[2].capture_stamp_s - 10.0, stamp_s=f[2].stamp_s - 10.0) if i >= 90 else f
              for i, f in enumerate(_frames())]
    with pytest.raises(IdentificationError, match=r"camera frames' clock steps back by 9.97 s after frame 89"):
        campaign_data_from_mcap(_archive(tmp_path / "step.mcap", _states(), frames))
    strays = _frames()
    for i in range(10, 170, 20):  # 8 strays in 180 frames: more than a stray or two, a damaged record
        strays[i] = _replace(strays[i], capture_stamp_s=1e9 + i, stamp_s=1e9 + i + 0.05)
    with pytest.raises(IdentificationError, match=r"8 of 180 camera frames are stamped far off"):
        campaign_data_from_mcap(_archive(tmp_path / "strays.mcap", _states(), strays))


# -- one bridge run (audit of 2026-11-30: two runs' states interleaved gave k -14/-15 %, λ +59 %, exit 0) --


def _other_run(states: list, epoch: str = "e2", bridge: str = "b2", shift_s: float = 0.001,
               offset_rad: float = 0.3) -> list:
    """``states`` as another bridge run's: ``shift_s`` later (stamp and receive time), θ ``offset_rad`` off."""
    return [(key, log_ns + int(shift_s * 1e9), msgspec.structs.replace(
        m, bridge=bridge, epoch=epoch, stamp_s=m.stamp_s + shift_s, theta_rad=[x + offset_rad for x in m.theta_rad]))
        for key, log_ns, m in states]


def _received_later(part: list, s: float = 20.0) -> list:
    """``part`` received ``s`` later (another run's states may then be received before it)."""
    return [(key, log_ns + int(s * 1e9), m) for key, log_ns, m in part]


def _commands(epoch: str, every: int = 10) -> list:
    """The campaign's controller's commands, each answering a state of the bridge run ``epoch``."""
    return [(bus.MOTOR_COMMAND, int(k * 2e6) + 3, bus.ForceCommand(
        seq=k + 1, stamp_s=k * 0.002, force_N=[10.0] * 4, source="law1", sender="ctl", epoch=epoch))
        for k in range(0, N_STATES, every)]


def test_states_of_two_bridge_runs_received_interleaved_are_refused_when_no_command_names_the_campaigns(tmp_path):
    """A second bridge on the bus, its states interleaved with the campaign's, both recorded (the
    recorder keeps every run until a command names the campaign's): fitted as one record."""
    mixed = _archive(tmp_path / "mixed.mcap", _states(), _other_run(_states()), _frames())
    with pytest.raises(IdentificationError, match=r"holds the states of 2 bridge runs received interleaved: bridge "
                                                  r"'b' run 'e' \(3000 states, stamped 0-5\.998 s\), bridge 'b2' run "
                                                  r"'e2' \(3000 states.*no command names the campaign's"):
        campaign_data_from_mcap(mixed)


def test_the_states_of_the_run_the_commands_answer_are_read_and_the_others_dropped_and_said(tmp_path):
    clean = campaign_data_from_mcap(_archive(tmp_path / "clean.mcap", _states(), _frames()))
    for name, other in (("interleaved", _other_run(_states())),  # during the campaign: told apart by its epoch
                        ("before", _other_run(_states()[:1000], shift_s=10.0))):  # before the first command
        campaign = [_states(), _frames(), _commands("e")]
        if name == "before":  # received before the campaign's, stamped on another clock
            campaign = [_received_later(part) for part in campaign]
        data = campaign_data_from_mcap(_archive(tmp_path / f"{name}.mcap", other, *campaign))
        np.testing.assert_array_equal(data.t_s, clean.t_s)
        np.testing.assert_array_equal(data.theta_rad, clean.theta_rad)
        n = len(other)
        assert len(data.notes) == 1 and data.notes[0].startswith(
            f"{n} motor state(s) of 1 other bridge run(s) dropped: bridge 'b2' run 'e2' ({n} states"), data.notes
        assert "kept bridge 'b' run 'e' (3000 states: the run the campaign's commands answer)" in data.notes[0]


def test_another_runs_states_received_before_the_campaigns_are_dropped_when_no_command_names_a_run(tmp_path):
    """An archive without commands (or none naming a run recorded): the run with the most states,
    another's kept out as long as none of its states was received within that run's span."""
    clean = campaign_data_from_mcap(_archive(tmp_path / "clean.mcap", _states(), _frames()))
    other = _other_run(_states()[:500], shift_s=10.0)  # another clock, received before: not the campaign's
    campaign = [_received_later(part) for part in (_states(), _frames(), _commands("gone"))]
    data = campaign_data_from_mcap(_archive(tmp_path / "before.mcap", other, *campaign))
    np.testing.assert_array_equal(data.theta_rad, clean.theta_rad)
    assert len(data.notes) == 1 and data.notes[0].startswith("500 motor state(s) of 1 other bridge run(s) dropped"), \
        data.notes
    assert "the run with the most states" in data.notes[0]


def test_commands_answering_two_bridge_runs_are_refused(tmp_path):
    """A bridge restarted mid-campaign: its second run's encoders have their own zero."""
    states, commands = _states(), _commands("e")
    restarted = states[:1500] + _other_run(states[1500:], epoch="e3", bridge="b", shift_s=0.0)
    commands = commands[:150] + [_replace(c, epoch="e3") for c in commands[150:]]
    with pytest.raises(IdentificationError, match=r"commands answer 2 bridge runs: bridge 'b' run 'e' \(1500 states.*"
                                                  r"bridge 'b' run 'e3' \(1500 states.*restarted mid-campaign"):
        campaign_data_from_mcap(_archive(tmp_path / "restart.mcap", restarted, _frames(), commands))


def test_another_controllers_commands_recorded_before_the_campaigns_own_do_not_refuse_it(tmp_path):
    """Review of session 49: until the recorder follows the campaign's controller it keeps every
    command on the bus; a few of another controller's, answering its own bridge's run, made the
    reader refuse a good archive as "the campaign's commands answer 2 bridge runs". The run is the
    one the campaign's controller (the sender of most commands) answers."""
    clean = campaign_data_from_mcap(_archive(tmp_path / "clean.mcap", _states(), _frames()))
    stray = [_replace(c, sender="other", epoch="e2") for c in _commands("e2")[:10]]
    other = _other_run(_states()[:100])
    data = campaign_data_from_mcap(_archive(tmp_path / "stray.mcap", _states(), _frames(), _commands("e"), stray, other))
    np.testing.assert_array_equal(data.theta_rad, clean.theta_rad)
    assert any("kept bridge 'b' run 'e'" in n and "the run the campaign's commands answer" in n for n in data.notes), \
        data.notes
    assert any("10 command(s) of 1 other controller(s) ('other') not counted" in n for n in data.notes), data.notes


def test_runs_read_as_columns_break_ties_and_keep_others_out_as_before(tmp_path):
    """Review of 2026-11-30: the reader folds motor states into columns as it reads them (a 577 s
    campaign's decoded states had taken 565 MB). Read in file order, runs and senders were then
    numbered in file order, not log-time order: on equal counts another run was kept. And a state
    of another run with another motor count refused the whole record, where it is dropped."""
    clean = campaign_data_from_mcap(_archive(tmp_path / "clean.mcap", _states(), _frames()))
    # Written in this order (the recorder's file order is not its log-time order across threads):
    # another run's 3000 states received 10 s after the campaign's, then the campaign's.
    later = _other_run(_states(), shift_s=10.0)
    tie = write_campaign(tmp_path / "tie.mcap", later + _states() + _frames(), {"campaign_id": "tie"})
    data = campaign_data_from_mcap(tie)
    np.testing.assert_array_equal(data.theta_rad, clean.theta_rad)  # the run first received, as before
    assert "kept bridge 'b' run 'e' (3000 states: the run with the most states" in data.notes[0], data.notes
    # Two controllers, as many commands each: the one first heard is the campaign's, whatever the file order.
    first = [_replace(c, sender="first") for c in _commands("e")]
    second = [(k, t + int(10e9), msgspec.structs.replace(c, sender="second", epoch="e2")) for k, t, c in _commands("e")]
    both = write_campaign(tmp_path / "senders.mcap", second + later + _states() + _frames() + first,
                          {"campaign_id": "senders"})
    data = campaign_data_from_mcap(both)
    np.testing.assert_array_equal(data.theta_rad, clean.theta_rad)
    assert any("the campaign's is 'first'" in n for n in data.notes), data.notes
    # Another run of 3 motors: dropped, not the record refused; the campaign's own run must be regular.
    three = [(k, t, msgspec.structs.replace(m, theta_rad=m.theta_rad[:3], force_applied_N=m.force_applied_N[:3]))
             for k, t, m in _other_run(_states()[:200])]
    data = campaign_data_from_mcap(_archive(tmp_path / "three.mcap", three, _states(), _frames(), _commands("e")))
    np.testing.assert_array_equal(data.theta_rad, clean.theta_rad)
    ragged = _states()
    ragged[1000] = _replace(ragged[1000], theta_rad=[0.0] * 3, force_applied_N=[10.0] * 3)
    with pytest.raises(IdentificationError, match=r"a motor state of 3 angles and 3 forces, its run's first had 4"):
        campaign_data_from_mcap(_archive(tmp_path / "ragged.mcap", ragged, _frames()))
