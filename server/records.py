"""The campaign index: one small JSON file per campaign next to its MCAP archive.

``<data_dir>/campaigns/<id>.mcap`` is the data; ``<id>.json`` is what the console lists and
filters without opening archives (kind, law, trajectory, status, progress, metrics). The JSON is
rewritten atomically (write, fsync, rename: :func:`bridge.archive.atomic_write`) on every change,
so a crash or a full disk leaves the previous version.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field

from bridge.archive import atomic_write, storage_reason
from bridge.small_file import read_input_file

log = logging.getLogger("xneck.campaigns")

#: ``degraded``: finished below the real-time quality thresholds (server.quality; reasons in ``quality``);
#: ``analysis_failed``: recorded, but its identification analysis failed (``identification_status``).
CampaignStatus = Literal["running", "finished", "degraded", "analysis_failed", "aborted", "interrupted", "failed"]
_ID = re.compile(r"^[A-Za-z0-9_.\-]{1,100}$")


class CampaignRecord(BaseModel):
    """What the API returns for a campaign. Angles in ``metrics`` are in degrees (report edge),
    forces in N, times in s; timestamps are UTC ISO 8601."""

    id: str
    kind: Literal["identification", "control"]
    law: str = Field(description="Law name, e.g. law2 or law2-no-pulleys.")
    trajectory: str = Field(description="Trajectory name.")
    trajectory_spec: dict[str, Any] = Field(default_factory=dict, description="Waypoints (deg), durations (s).")
    duration_s: float = 0.0
    parameter_set: str
    target: Literal["twin", "robot"]
    pace: Literal["lockstep", "realtime"] = "lockstep"
    seed: int = Field(default=0, description="Seed of the twin's sensor noise (0 on the robot).")
    truth: str = Field(default="", max_length=256, description="What the twin simulated (twin/sim/truth.py): model, "
                       "robot or a truth file's name (GET /api/truths); empty on the robot.")
    estimator: str = Field(default="", max_length=32, description="Identification: Table 2's estimator its "
                           "analysis was asked for (auto, iv, ols, wls, loadfriction, outputerror); empty for control.")
    creep_time_s: float | None = Field(default=None, description="Identification: the line's creep time constant "
                                       "(s) held in its analysis; null: estimated from the record.")
    status: CampaignStatus = "running"
    progress: float = Field(default=0.0, ge=0.0, le=1.0)
    message: str = ""
    created_at: str = ""
    ended_at: str = ""
    metrics: dict[str, Any] | None = None
    quality: dict[str, Any] | None = Field(default=None, description="Real-time quality of the run (server.quality): "
                                           "ticks, rate_hz, deadline_misses, record_gaps, messages_lost, "
                                           "thresholds, and reasons (why it is degraded).")
    identification: dict[str, Any] | None = None
    identification_status: str = ""
    scene_messages: int = 0
    mcap_bytes: int = 0
    running_on: str = Field(default="", max_length=256, description="The controller service that still runs this "
                            "campaign though this console does not record it (it was restarted during it); "
                            "POST .../stop stops it there. Empty otherwise; true only while it runs.")


#: The most bytes a campaign record may have: an identification campaign's, its tables included,
#: is some tens of kB; a FIFO or a device in its place must neither block nor fill the memory.
RECORD_MAX_BYTES = 16 * 1024 * 1024


def valid_id(campaign_id: str) -> bool:
    return bool(_ID.fullmatch(campaign_id)) and not campaign_id.startswith(".")


class CampaignIndex:
    """Reads and writes the JSON records in one directory."""

    def __init__(self, directory: Path) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)

    def mcap(self, campaign_id: str) -> Path:
        return self.dir / f"{campaign_id}.mcap"

    def json(self, campaign_id: str) -> Path:
        return self.dir / f"{campaign_id}.json"

    def figures(self, campaign_id: str) -> Path:
        return self.dir / f"{campaign_id}_figures"

    def save(self, record: CampaignRecord) -> None:
        """Raises ``OSError`` on a storage fault (the previous version stays)."""
        atomic_write(self.json(record.id), record.model_dump_json(indent=1).encode())

    def load_all(self, errors: dict[str, str] | None = None) -> list[CampaignRecord]:
        """Every readable record; a file that cannot be read, or is not a record this version
        reads (damaged, hand-edited, from a later version), is reported in ``errors`` (name ->
        reason) and skipped, never an exception. Nothing here changes a file: a record skipped
        is left as it is (:meth:`server.campaigns.CampaignManager.recover_all` too)."""
        out = []
        for p in sorted(self.dir.glob("*.json")):
            try:
                # A regular file of bounded size: a FIFO here had blocked the console's start for
                # ever (review of session 53).
                rec = CampaignRecord.model_validate_json(read_input_file(p, RECORD_MAX_BYTES))
            except ValueError as exc:
                # Reported: the start-up had gone on to rebuild it from its archive, over it.
                reason = f"not a campaign record this version reads ({str(exc).splitlines()[0][:300]}): left as it is"
                log.error("not loading %s: %s", p, reason)
                if errors is not None:
                    errors[p.name] = reason
                continue
            except OSError as exc:
                log.error("cannot read %s: %s", p, storage_reason(exc))
                if errors is not None:
                    errors[p.name] = storage_reason(exc)
                continue
            # The id names the record's files (save, delete, the archive): one that is not its own
            # file's name, e.g. "../../x", made start-up write outside the data directory (audit of
            # 2026-11-27). Such a record is left alone and reported.
            if rec.id != p.stem or not valid_id(rec.id):
                reason = f"its id {rec.id[:120]!r} is not its file name {p.stem!r}"
                log.error("not loading the campaign record %s: %s", p, reason)
                if errors is not None:
                    errors[p.name] = reason
                continue
            out.append(rec)
        return out
