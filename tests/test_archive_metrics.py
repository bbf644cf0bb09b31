"""The campaign metrics read from an archive as columns (server/archive_metrics.py).

Audit of 2026-11-30: the console's metrics of a 600 s campaign decoded and kept every controller
status and motor command (690 MB, 9 s); they are folded into columns now (144 MB, 4 s). These tests
hold the columns to what the messages, decoded and kept, gave: holds left out, a tick matched to the
command of its stamp (the last logged when several), frames with a missing joint and of a second
camera left out, and mixed widths refused.
"""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from bridge import bus
from bridge.archive import write_campaign
from controller.metrics import campaign_metrics
from server.archive_metrics import metrics_from_archive


def _status(k: int, t: float, *, holding: bool = False, joints: int = 3) -> bus.ControllerStatus:
    return bus.ControllerStatus(
        seq=k, stamp_s=t, law="law1", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
        saturated=[k % 7 == 0, False, k % 11 == 0, False], alpha_hat_rad=[0.1 * np.sin(t + j) for j in range(joints)],
        alpha_d_rad=[0.1 * np.sin(t + j + 0.05) for j in range(joints)], e_rad=[0.0] * joints, holding=holding)


def _command(k: int, t: float, force: float, width: int = 4) -> bus.ForceCommand:
    return bus.ForceCommand(seq=k, stamp_s=t, force_N=[force + j for j in range(width)], source="law1", sender="c",
                            epoch="e")


def _frame(k: int, t: float, source: str = "cam", blind: bool = False) -> bus.CameraAlpha:
    alpha = [0.1 * np.sin(t + j) + 0.01 for j in range(3)]
    return bus.CameraAlpha(seq=k, stamp_s=t + 0.03, capture_stamp_s=t,
                           alpha_ip_rad=[None, *alpha[1:]] if blind else alpha, source=source)


def _campaign(n: int = 600):
    """Ticks at 500 Hz (every 50th holding, every 40th unanswered), each answered twice for every
    13th (the later-logged force wins), frames at 30 Hz (every 9th blind, a second camera's too)."""
    msgs = []
    for k in range(n):
        t, log = 0.002 * k, int(0.002 * k * 1e9)
        msgs.append((bus.CONTROLLER_STATUS, log + 2, _status(k, t, holding=k % 50 == 49)))
        if k % 40 != 39:
            msgs.append((bus.MOTOR_COMMAND, log + 3, _command(k, t, 20.0 + 0.01 * k)))
        if k % 13 == 0:
            msgs.append((bus.MOTOR_COMMAND, log + 5, _command(k, t, 90.0)))
    for k in range(int(n * 0.002 * 30)):
        t = k / 30
        msgs.append((bus.CAMERA_ALPHA, int(t * 1e9) + 4, _frame(k, t, blind=k % 9 == 8)))
        msgs.append((bus.CAMERA_ALPHA, int(t * 1e9) + 6, _frame(k, t, source="other")))
    return msgs


def _reference(msgs) -> dict:
    """The metrics computed from the messages as they were kept before (decoded, in log-time order)."""
    ordered = sorted(msgs, key=lambda m: m[1])
    status = [m for key, _, m in ordered if key == bus.CONTROLLER_STATUS and not m.holding]
    cmds = {m.stamp_s: m.force_N for key, _, m in ordered if key == bus.MOTOR_COMMAND}
    status = [m for m in status if m.stamp_s in cmds]
    frames = [m for key, _, m in ordered if key == bus.CAMERA_ALPHA]
    frames = [m for m in frames if m.source == frames[0].source and None not in m.alpha_ip_rad]
    return campaign_metrics(
        t_s=np.array([m.stamp_s for m in status]), alpha_hat=np.array([m.alpha_hat_rad for m in status]),
        alpha_d=np.array([m.alpha_d_rad for m in status]), force_N=np.array([cmds[m.stamp_s] for m in status]),
        saturated=np.array([m.saturated for m in status]), t_ip_s=np.array([m.capture_stamp_s for m in frames]),
        alpha_ip=np.array([m.alpha_ip_rad for m in frames]))


def test_the_folded_metrics_are_those_of_the_messages_kept(tmp_path) -> None:
    msgs = _campaign()
    got = metrics_from_archive(write_campaign(tmp_path / "c.mcap", msgs, {"campaign_id": "c"}))
    assert got == _reference(msgs)
    assert got["ticks"] == sum(k % 50 != 49 and (k % 40 != 39 or k % 13 == 0) for k in range(600)) == 578
    assert got["force_max_N"] == [90.0, 91.0, 92.0, 93.0]  # the later-logged of two commands of a stamp
    assert isinstance(got["saturated_ticks"], int) and got["saturated_ticks"] > 0 and got["camera_frames"] == 32


def test_no_tick_or_mixed_widths_are_refused_as_before(tmp_path) -> None:
    held = [(bus.CONTROLLER_STATUS, k + 1, _status(k, 0.002 * k, holding=True)) for k in range(10)]
    with pytest.raises(ValueError, match="no controller status recorded"):
        metrics_from_archive(write_campaign(tmp_path / "held.mcap", held, {"campaign_id": "h"}))
    # a tick of another width that a command answers
    mixed = _campaign(100) + [(bus.CONTROLLER_STATUS, int(0.1e9) + 7, _status(50, 0.1, joints=2))]
    with pytest.raises(ValueError, match=r"controller statuses of different widths"):
        metrics_from_archive(write_campaign(tmp_path / "mixed.mcap", mixed, {"campaign_id": "m"}))
    # the command a tick takes (the last logged of its stamp) of another width
    wide = _campaign(100) + [(bus.MOTOR_COMMAND, int(0.1e9) + 9, _command(50, 0.1, 5.0, width=5))]
    with pytest.raises(ValueError, match="motor commands of different widths"):
        metrics_from_archive(write_campaign(tmp_path / "wide.mcap", wide, {"campaign_id": "w"}))


@pytest.mark.parametrize("stray", [
    (bus.CONTROLLER_STATUS, int(5e9), _status(999, 10.0, joints=2)),  # a tick no command answers
    (bus.MOTOR_COMMAND, int(5e9), _command(5000, 10.0, 5.0, width=5)),  # a command answering no tick
    (bus.MOTOR_COMMAND, 0, _command(5000, 10.0, 5.0, width=5)),  # the same, first in the file
    (bus.MOTOR_COMMAND, 0, _command(5000, 10.0, 5.0, width=0)),  # an empty one, first in the file
], ids=["unanswered-tick", "stray-command", "stray-command-first", "empty-command-first"])
def test_a_message_of_another_width_that_no_tick_uses_is_harmless_as_it_was(tmp_path, stray) -> None:
    """Review of session 51: the first message's width was taken for all, so a stray command first
    in the file refused the campaign's metrics, an empty one gave empty forces, and a tick of
    another width no command answered refused them too; the messages kept had given the metrics."""
    got = metrics_from_archive(write_campaign(tmp_path / "s.mcap", [stray, *_campaign(100)], {"campaign_id": "s"}))
    assert got == _reference(_campaign(100))


def test_a_campaign_without_a_camera_has_its_metrics_and_alpha_hat_against_alpha_d_of_other_widths_is_refused(
        tmp_path) -> None:
    """Review of session 51: a campaign without α_IP (no camera started) had no metrics at all
    ("cannot reshape array of size 0"); ticks whose α^d has fewer joints than α̂ were broadcast
    into wrong errors."""
    no_camera = [m for m in _campaign(100) if m[0] != bus.CAMERA_ALPHA]
    got = metrics_from_archive(write_campaign(tmp_path / "nocam.mcap", no_camera, {"campaign_id": "n"}))
    assert isinstance(got["ticks"], int) and got["ticks"] > 0 and got["camera_frames"] == 0 and got["e_alpha_mean_deg"] is None and got["e_mean_deg"] == _reference(_campaign(100))["e_mean_deg"]
    short_d = [(key, log, msgspec.structs.replace(m, alpha_d_rad=m.alpha_d_rad[:1]) if key == bus.CONTROLLER_STATUS else m)
               for key, log, m in _campaign(100)]
    with pytest.raises(ValueError, match="3 estimated and 1 desired joint angles"):
        metrics_from_archive(write_campaign(tmp_path / "short.mcap", short_d, {"campaign_id": "s"}))
