"""Replay of an archived campaign onto the bus, so the dashboard and the 3D view show it as live.

Messages are published with their recorded log-time spacing divided by ``speed``. Keys that
actuate anything (force commands, e-stop, campaign requests) are never replayed: a replay must not
move a robot. A campaign run by a controller service (``xneck up``) records the start request the
console sent it; replayed, that request started the campaign again on the service, and the robot
moved (audit of 2026-11-27).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import zenoh

from bridge import bus
from bridge.archive_read import read_campaign
from bridge.session import REPLAYED, BusPublisher, publisher

NEVER_REPLAYED: frozenset[type[bus.BusMessage]] = frozenset({bus.ForceCommand, bus.EStop, bus.CampaignRequest})


def _replayed(topic: str) -> bool:
    """Whether a topic's messages are replayed (the others are not even decoded: the Foxglove
    scene is half of an archive's decoded size)."""
    msg_type = bus.message_type(bus.key_of_topic(topic))  # by type: requests are also addressed to one service
    return msg_type is not None and msg_type not in NEVER_REPLAYED


class Replay:
    """One replay in a daemon thread, read from ``path`` when built (a bad file raises here) and
    published from :meth:`start` on; :meth:`stop` ends it within one message interval.
    ``speed``: recorded time per wall-clock time (1 = as recorded)."""

    def __init__(self, session: zenoh.Session, campaign_id: str, path: Path, speed: float = 1.0) -> None:
        if not speed > 0:
            raise ValueError("speed must be > 0")
        self.campaign_id = campaign_id
        self.speed = speed
        self.published = 0
        self.total = 0
        self.error = ""
        self._stop = threading.Event()
        campaign = read_campaign(path, keys=_replayed)  # before the thread: a bad file is the caller's error
        self._messages: list[tuple[int, str, bus.BusMessage]] = []
        for topic, msgs in campaign.topics.items():
            key = bus.key_of_topic(topic)
            self._messages += [(t, key, m) for t, m in msgs if isinstance(m, bus.BusMessage)]
        self._messages.sort(key=lambda x: x[0])
        self.total = len(self._messages)
        self._session = session
        self._pubs: dict[str, BusPublisher[bus.BusMessage]] = {}
        self._thread = threading.Thread(target=self._run, name=f"replay:{campaign_id}", daemon=True)

    def start(self) -> None:
        """Publish from now on. Separate from reading the file so that the console can hold the
        robot for this replay while the (long) read goes on, and start it only if still wanted."""
        self._pubs = {key: publisher(self._session, key) for key in {k for _, k, _ in self._messages}}
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    @property
    def progress(self) -> float:
        return self.published / self.total if self.total else 1.0

    def _run(self) -> None:
        try:
            if not self._messages:
                return
            t0_log, t0_wall = self._messages[0][0], time.monotonic()
            for log_ns, key, msg in self._messages:
                due = t0_wall + (log_ns - t0_log) / 1e9 / self.speed
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                if self._stop.is_set():
                    return
                self._pubs[key].put(msg, attachment=REPLAYED)  # never the bridge's word now
                self.published += 1
        except Exception as exc:  # noqa: BLE001 - shown in the status, not lost in a thread
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            for pub in self._pubs.values():
                pub.close()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread.ident is not None:  # started
            self._thread.join(timeout_s)

    def status(self) -> dict[str, object]:
        return {"campaign_id": self.campaign_id, "running": self.running, "starting": False, "progress": self.progress,
                "published": self.published, "total": self.total, "speed": self.speed, "error": self.error}
