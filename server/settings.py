"""Typed settings of the experiment console, from arguments or ``XNECK_*`` environment variables.

Every field can be set as ``XNECK_<FIELD>`` (e.g. ``XNECK_PORT=8001``, ``XNECK_TOKEN=...``).
Defaults are safe for a lab bench: the HTTP server and the viser view bind to loopback only.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

TOKEN_FILE = "token"


class Settings(BaseSettings):
    """Configuration of one console server (one lab, one robot or twin, one data directory)."""

    model_config = SettingsConfigDict(env_prefix="XNECK_", extra="ignore")

    host: str = Field("127.0.0.1", description="HTTP bind address (loopback unless a lab opens it on purpose).")
    port: int = Field(8000, ge=0, le=65535, description="HTTP port.")
    viser_port: int = Field(0, ge=0, le=65535, description="Port of the viser 3D view; 0 = a free one.")
    data_dir: Path = Field(Path("data"), description="Campaign archives, their JSON index, parameter sets.")
    token: str | None = Field(None, description="Bearer token of mutating endpoints; generated if absent.")
    hub: str = Field("tcp/127.0.0.1:0", description="Zenoh endpoint the console listens on (the hub); "
                     "port 0 picks a free loopback port at start-up.")
    connect: list[str] = Field(default_factory=list, description="Zenoh endpoints to connect to (robot mode: "
                               "the bridge).")
    mode: Literal["twin", "robot"] = Field("twin", description="What campaigns drive by default.")
    pace: Literal["lockstep", "realtime"] = Field("realtime", description="Twin campaigns: lockstep (fast, "
                                                   "deterministic) or real time (500 Hz, for watching).")
    live_rate_hz: float = Field(30.0, gt=0, le=200, description="Rate of live frames sent to browsers (Hz).")
    scene_rate_hz: float = Field(30.0, gt=0, le=200, description="Update rate of the viser scene (Hz).")
    campaign_timeout_s: float = Field(900.0, gt=0, description="Abort a campaign after this long (wall, s); a "
                                      "campaign in real time needs its trajectory's duration, 10 % and 10 s more within it.")
    viser: bool = Field(True, description="Start the viser 3D view.")
    twin_truth: str = Field("model", description="With a controller service on the bus (`xneck up`): what the "
                            "stack's twin bridge simulates, model, robot or a truth file (twin/sim/truth.py).")
    twin_seed: int = Field(0, ge=0, le=2**31 - 1, description="With a controller service on the bus: the seed of "
                           "the stack's twin bridge.")
    twin_alpha_ip: Literal["noise", "camera"] | None = Field(None, description="With a controller service on "
                                                             "the bus: the α_IP of the stack's twin bridge (`xneck up "
                                                             "--alpha-ip`), the one camera its campaigns record "
                                                             "(server.quality); unset: the first camera seen.")
    twin_camera: str | None = Field(None, min_length=1, max_length=64, description="With a controller service on the "
                                    "bus: the instance of the stack's camera process (`xneck up --alpha-ip camera`), "
                                    "the one camera of its source its campaigns record (server.quality); unset: the "
                                    "first of that source seen.")
    stack: bool = Field(False, description="This console is an `xneck up` stack's (`xneck up` sets it): campaigns "
                        "go to the stack's controller service, and with none on the bus (being restarted, stopped) a campaign "
                        "is refused (503), never run on a twin and a controller of the console's own beside the "
                        "stack's bridge.")
    min_free_mb: float = Field(64.0, ge=0, description="A campaign starts only with this much free space (MB) "
                               "in the archive directory (else 507).")
    allowed_hosts: list[str] = Field(default_factory=list, description="Host names the console answers to besides "
                                     "its bind address and loopback (DNS-rebinding guard); with --host 0.0.0.0 and "
                                     "this list empty, any.")
    allowed_origins: list[str] = Field(default_factory=list, description="Web origins (scheme://host:port) allowed "
                                       "to read live data besides the console's own.")
    workspace_grid: int = Field(31, ge=5, le=61, description="Points per α axis of the 3-X workspace maps "
                                "(odd, over ±90°); the cost grows with its cube (31: ≈2 s on 2 cores).")

    @field_validator("twin_camera")
    @classmethod
    def _camera_with_its_source(cls, camera: str | None, info: ValidationInfo) -> str | None:
        # the camera process named is of the source --twin-alpha-ip camera records: alone it was ignored
        if camera is not None and info.data.get("twin_alpha_ip") != "camera":
            raise ValueError("names the stack's camera process, whose α_IP the campaigns record only with "
                             "--twin-alpha-ip camera (xneck up --alpha-ip camera sets both)")
        return camera

    @field_validator("twin_truth")
    @classmethod
    def _truth_loads(cls, truth: str) -> str:
        from twin.sim.truth import TRUTHS, TruthError, check_truth

        try:
            check_truth(truth)
        except TruthError as exc:
            raise ValueError(str(exc)) from None
        return truth if truth in TRUTHS else str(Path(truth).resolve())

    @field_validator("workspace_grid")
    @classmethod
    def _odd_grid(cls, n: int) -> int:
        if n % 2 == 0:
            raise ValueError(f"must be odd so that α = 0 is on the grid, got {n}")
        return n


def resolve_token(settings: Settings) -> tuple[str, bool]:
    """The bearer token: from the settings, else ``<data_dir>/token``, else a new one written there
    (mode 600). Returns ``(token, generated_now)`` so the caller can print a new token once."""
    if settings.token:
        return settings.token, False
    path = Path(settings.data_dir) / TOKEN_FILE
    if path.exists():
        token = path.read_text().strip()
        if token:
            return token, False
    path.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(24)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token, True
