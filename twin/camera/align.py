"""Offline alignment of a video with a recorded campaign (3-X paper §4.2: the prototype's α_IP
was computed offline from the video, then put beside the encoder data).

1. :func:`measure_video`: α_IP of every frame (``twin.camera.detect``), on the video's own clock
   (:class:`twin.camera.source.FileSource`: the container's time, else frame count / fps; an
   undecodable frame is skipped and the later ones keep their time); missing joints are NaN. The
   frames the video lacked (undecodable, skipped by its clock, or missing from a truncated file)
   are counted against what the container declares, and go into the provenance. A video whose
   camera the detector finds moved since its calibration (docs/camera.md, "Camera moved") is
   refused at the first such frame, with the shift and what to do (:data:`RECALIBRATE_VIDEO`):
   none of its joints is measured there, and the alignment would fail for want of α, or leave a
   gap, without saying why.
2. :func:`campaign_reference`: the campaign's α on its clock (the motor states' ``stamp_s``): the
   twin's truth if recorded, else the controller's α̂ (eq. 33 from the encoders).
3. :func:`align`: the campaign time of a frame is t_c = offset + (1 + drift)·t_video. A coarse
   search over every offset at half a frame period (the whole overlap range) minimises the mean
   squared difference between the detected α and the reference interpolated at t_c; a local
   Nelder-Mead search then refines offset (and drift). The mean over joints and frames of the
   squared error is used, so a joint missing in some frames only drops those samples.
   A periodic excitation has as many minima as periods in the overlap: the lowest one wins, the
   runner-up is reported so an ambiguous alignment is visible.
4. :func:`write_aligned`: a copy of the campaign MCAP (every channel and metadata record as
   recorded) whose ``/xneck/camera/alpha_ip`` channel holds the aligned α_IP (source
   ``file:<video>``), and a metadata record ``xneck.camera.alignment`` with the provenance
   (video file and hash, offset, drift, residual, reference, counts). Camera messages already in
   the campaign (the twin's white-noise camera) are replaced, and counted in the provenance.
   With an image rate, JPEGs of the frames go on ``/xneck/camera/image`` as
   ``foxglove.CompressedImage`` (JSON), so Foxglove plays the video beside the plots.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from mcap.writer import CompressionType, Writer

from bridge import bus
from bridge.archive import COMPRESSED_IMAGE_SCHEMA, IMAGE_SCHEMA_NAME, IMAGE_TOPIC, ArchiveError, compressed_image
from bridge.archive_chunks import BoundedReader
from bridge.archive_read import check_finished
from twin.camera.detect import Detector, moved_reason
from twin.camera.source import FileSource

ALIGNMENT_METADATA = "xneck.camera.alignment"
#: What to do about a video filmed by a camera moved since its calibration (:func:`measure_video`).
RECALIBRATE_VIDEO = ("its α cannot be measured with this calibration: redo the extrinsic calibration on a frame of "
                     "the video with the neck at rest (docs/camera.md, Calibration) and align again with --calibration")
MOTOR_TOPIC = bus.mcap_topic(bus.MOTOR_STATE)
CAMERA_TOPIC = bus.mcap_topic(bus.CAMERA_ALPHA)


#: The provenance's numeric fields. MCAP metadata holds strings only; ``xneck camera align --json``
#: prints these as JSON numbers (:func:`provenance_json`), which jq and scripts compare as such.
PROVENANCE_INTEGERS = ("frames", "frames_used", "frames_declared", "frames_lost", "frames_written", "missing_joints",
                       "replaced_camera_messages", "images", "replaced_images")
PROVENANCE_FLOATS = ("video_fps", "offset_s", "drift", "rms_deg", "runner_up_offset_s", "runner_up_rms_deg")


def provenance_json(provenance: dict[str, str]) -> dict[str, str | int | float]:
    """The provenance record of :func:`write_aligned` (strings, as the archive stores it) with its
    numeric fields as numbers: the same figures as the archive's record, not new ones. A non-finite
    figure (a video without a frame rate: nan) stays a float, which strict JSON prints as null."""
    out: dict[str, str | int | float] = dict(provenance)
    for name in PROVENANCE_INTEGERS:
        if name in provenance:
            out[name] = int(provenance[name])
    for name in PROVENANCE_FLOATS:
        if name in provenance:
            out[name] = float(provenance[name])
    return out


class AlignmentError(ValueError):
    """The video and the campaign cannot be aligned (no overlap, no reference, unreadable file)."""


@dataclass
class VideoAlpha:
    """α_IP per frame: ``t_s`` (M,) video time, ``alpha_rad`` (M, N) with NaN for a missing joint."""

    name: str
    fps: float
    t_s: np.ndarray
    alpha_rad: np.ndarray
    confidence: np.ndarray
    jpeg: dict[int, bytes] | None = None  # frame index -> JPEG of the frames kept for the archive
    declared: int = 0  # frames the container declares (0: it declares none)
    lost: int = 0  # frames the video lacked (FileSource.dropped)
    loss: str = ""  # what it lacked, one line (FileSource.loss); "" for a whole video


@dataclass
class Reference:
    name: str  # "truth" or "alpha_hat"
    t_s: np.ndarray
    alpha_rad: np.ndarray


@dataclass(frozen=True)
class Alignment:
    offset_s: float
    drift: float
    rms_deg: float
    frames_used: int
    runner_up_offset_s: float
    runner_up_rms_deg: float

    def campaign_time(self, t_video_s: np.ndarray) -> np.ndarray:
        return self.offset_s + (1.0 + self.drift) * np.asarray(t_video_s, dtype=float)


def measure_video(path: str | Path, detector: Detector, max_frames: int | None = None,
                  image_rate_hz: float = 0.0, jpeg_quality: int = 75) -> VideoAlpha:
    """α_IP of every frame; with ``image_rate_hz`` > 0, JPEGs of frames at about that rate too.
    Raises :class:`AlignmentError` at the first frame the detector finds the camera moved on (its
    shift in px, its video time in s, and :data:`RECALIBRATE_VIDEO`)."""
    source = FileSource(path)
    t, alpha, conf = [], [], []
    jpeg: dict[int, bytes] = {}
    every = max(1, round(source.fps / image_rate_hz)) if image_rate_hz > 0 else 0
    moved = ""
    try:
        while max_frames is None or len(t) < max_frames:
            frame = source.read()
            if frame is None:
                break
            found = detector.detect(frame.image)
            if found.reason:  # said here, not raised: this try re-words a ValueError
                moved = moved_reason(detector.moved_px or math.nan, detector.config.moved_px, RECALIBRATE_VIDEO,
                                     f", found at {frame.capture_s:.3f} s of the video (frame {len(t) + 1})")
                break
            if every and len(t) % every == 0:
                ok, buf = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
                if ok:
                    jpeg[len(t)] = buf.tobytes()
            t.append(frame.capture_s)
            alpha.append([math.nan if a is None else a for a in found.alpha_rad])
            conf.append(found.confidence)
    except ValueError as exc:
        raise AlignmentError(f"{path}: {exc}") from None
    finally:
        source.close()
    if moved:
        raise AlignmentError(f"{path}: {moved}")
    if len(t) < 10:
        raise AlignmentError(f"{path}: {len(t)} frames; at least 10 are needed")
    loss = source.loss()
    return VideoAlpha(Path(path).name, source.fps, np.array(t), np.array(alpha, dtype=float), np.array(conf, dtype=float),
                      jpeg or None, declared=source.declared, lost=source.dropped, loss="" if loss is None else loss.text)


def _iter_raw(path: Path):
    try:
        check_finished(path)  # a truncated file: the console repairs it (a raw reader's error said nothing)
    except ArchiveError as exc:
        raise AlignmentError(str(exc)) from None
    try:
        with open(path, "rb") as f:
            reader = BoundedReader(f, validate_crcs=True)
            yield from reader.iter_messages(log_time_order=True)
    except FileNotFoundError:
        raise AlignmentError(f"{path}: no such campaign file") from None
    except AlignmentError:
        raise
    except Exception as exc:  # noqa: BLE001 - mcap raises many types on a damaged file
        raise AlignmentError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None


def campaign_reference(path: str | Path, which: str = "auto") -> Reference:
    """The campaign's α (rad) on its clock: ``truth``, ``alpha_hat`` or ``auto`` (α̂ if recorded,
    else the twin's truth). ``auto`` takes α̂ first, what a prototype's campaign has: a twin's
    campaign aligned on its truth was an easier test than the robot's (truth audit of 2026-12-01);
    ``truth`` asks for it, e.g. to check the alignment itself on the twin."""
    if which not in ("auto", "truth", "alpha_hat"):
        raise AlignmentError(f"reference {which!r}: choose auto, truth or alpha_hat")
    series: dict[str, list[tuple[float, list[float]]]] = {"truth": [], "alpha_hat": []}
    topics = {bus.mcap_topic(bus.TWIN_TRUTH): ("truth", bus.Truth, "alpha_rad"),
              bus.mcap_topic(bus.CONTROLLER_STATUS): ("alpha_hat", bus.ControllerStatus, "alpha_hat_rad")}
    for _schema, channel, message in _iter_raw(Path(path)):
        entry = topics.get(channel.topic)
        if entry is None:
            continue
        name, msg_type, field = entry
        try:
            msg = bus.decode(msg_type, message.data)
        except bus.BusDecodeError:
            continue  # another schema version or a damaged message: not a reference sample
        series[name].append((msg.stamp_s, getattr(msg, field)))
    order = ["alpha_hat", "truth"] if which == "auto" else [which]
    for name in order:
        samples = series[name]
        if len(samples) >= 10:
            t = np.array([s[0] for s in samples])
            a = np.array([s[1] for s in samples], dtype=float)
            t, keep = np.unique(t, return_index=True)  # a lockstep twin repeats its last state
            return Reference(name, t, a[keep])
    raise AlignmentError(f"{path}: no {' or '.join(order)} recorded to align the video with")


def _mse(video: VideoAlpha, ref: Reference, offset: float, drift: float, min_frames: int) -> tuple[float, int]:
    tc = offset + (1.0 + drift) * video.t_s
    inside = (tc >= ref.t_s[0]) & (tc <= ref.t_s[-1])
    if inside.sum() < min_frames:
        return math.inf, int(inside.sum())
    err = []
    for j in range(video.alpha_rad.shape[1]):
        a = video.alpha_rad[inside, j]
        ok = np.isfinite(a)
        err.append(a[ok] - np.interp(tc[inside][ok], ref.t_s, ref.alpha_rad[:, j]))
    e = np.concatenate(err)
    return (float(np.mean(e**2)) if len(e) else math.inf), int(inside.sum())


#: deg: the residual above which a video is not this campaign's (a match is within about 1°, the
#: camera's noise and α̂'s model error; another motion left 7-28°, written with exit 0: user audit
#: of session 45)
ALIGN_RMS_MAX_DEG = 4.0
#: the clock drift (s/s) beyond which an alignment is not a clock's: a crystal is within 1e-4, a
#: container declaring 30 fps for 29.97 is 1e-3 off; the audit's wrong video fitted -1.08
ALIGN_DRIFT_MAX = 5e-3


def align(video: VideoAlpha, ref: Reference, estimate_drift: bool = True, min_overlap: float = 0.5) -> Alignment:
    """Offset (s) and drift of the video's clock against the campaign's (see the module doc).
    Raises :class:`AlignmentError` when the best one is no match: a residual above
    ``ALIGN_RMS_MAX_DEG`` or a drift beyond ``ALIGN_DRIFT_MAX`` (another campaign's video)."""
    if video.alpha_rad.shape[1] != ref.alpha_rad.shape[1]:
        raise AlignmentError(f"the video has {video.alpha_rad.shape[1]} joints, the campaign {ref.alpha_rad.shape[1]}")
    min_frames = max(10, int(min_overlap * len(video.t_s)))
    step = 0.5 / video.fps
    lo, hi = ref.t_s[0] - video.t_s[-1], ref.t_s[-1] - video.t_s[0]
    offsets = np.arange(lo, hi + step, step)
    costs = np.array([_mse(video, ref, o, 0.0, min_frames)[0] for o in offsets])
    if not np.isfinite(costs).any():
        raise AlignmentError(f"the video ({video.t_s[-1] - video.t_s[0]:.1f} s) and the campaign "
                             f"({ref.t_s[-1] - ref.t_s[0]:.1f} s) never overlap on {min_overlap:.0%} of the frames")
    best = int(np.argmin(costs))
    # Runner-up: the best offset at least one second away from the winner (another period).
    far = np.abs(offsets - offsets[best]) >= 1.0
    runner = int(np.argmin(np.where(far, costs, np.inf))) if far.any() else best
    from scipy.optimize import minimize

    if estimate_drift:
        def cost2(x: np.ndarray) -> float:
            return _mse(video, ref, x[0], x[1] * 1e-3, min_frames)[0]

        res = minimize(cost2, np.array([offsets[best], 0.0]), method="Nelder-Mead",
                       options={"xatol": 1e-5, "fatol": 1e-12, "initial_simplex": [[offsets[best], 0.0], [offsets[best] + step, 0.0],
                                                                                   [offsets[best], 0.5]]})
        offset, drift = float(res.x[0]), float(res.x[1]) * 1e-3
    else:
        res = minimize(lambda x: _mse(video, ref, x[0], 0.0, min_frames)[0], np.array([offsets[best]]), method="Nelder-Mead",
                       options={"xatol": 1e-5, "fatol": 1e-12, "initial_simplex": [[offsets[best]], [offsets[best] + step]]})
        offset, drift = float(res.x[0]), 0.0
    mse, used = _mse(video, ref, offset, drift, min_frames)
    rms_deg = math.degrees(math.sqrt(mse))
    if not rms_deg <= ALIGN_RMS_MAX_DEG or abs(drift) > ALIGN_DRIFT_MAX:
        raise AlignmentError(f"the video does not match this campaign's motion: its best alignment (offset "
                             f"{offset:+.4f} s, drift {drift * 1e6:+.0f} ppm) leaves {rms_deg:.2f}° rms against its "
                             f"{ref.name} over {used} frames (a match: within {ALIGN_RMS_MAX_DEG:g}° and "
                             f"{ALIGN_DRIFT_MAX * 1e6:.0f} ppm); is it another campaign's video?")
    return Alignment(offset_s=offset, drift=drift, rms_deg=rms_deg, frames_used=used,
                     runner_up_offset_s=float(offsets[runner]),
                     runner_up_rms_deg=math.degrees(math.sqrt(costs[runner])) if np.isfinite(costs[runner]) else math.inf)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_aligned(campaign: str | Path, out: str | Path, video_path: str | Path, video: VideoAlpha,
                  alignment: Alignment, reference: str, software: str = "") -> dict[str, str]:
    """Copy ``campaign`` to ``out`` (never overwritten) with the aligned α_IP on ``/xneck/camera/alpha_ip``
    and the provenance record; returns the provenance."""
    campaign, out = Path(campaign), Path(out)
    if out.resolve() == campaign.resolve():
        raise AlignmentError("the output must be a new file, not the campaign itself")
    records = list(_iter_raw(campaign))
    with open(campaign, "rb") as f:
        metadata = [(m.name, dict(m.metadata)) for m in BoundedReader(f).iter_metadata()]
    # Campaign clock → recorder log time, from the motor states (for the new messages' log_time).
    stamps, logs = [], []
    for _schema, channel, message in records:
        if channel.topic == MOTOR_TOPIC:
            stamps.append(message.publish_time * 1e-9)
            logs.append(message.log_time)
    tc = alignment.campaign_time(video.t_s)
    if stamps:
        s, idx = np.unique(np.array(stamps), return_index=True)
        log_of = np.interp(tc, s, np.array(logs, dtype=float)[idx])
    else:
        log_of = tc * 1e9
    replaced = sum(1 for _s, c, _m in records if c.topic == CAMERA_TOPIC)
    new = []
    for k, (t, row, conf) in enumerate(zip(tc, video.alpha_rad, video.confidence)):
        if not (math.isfinite(t) and t >= 0):
            continue
        msg = bus.CameraAlpha(seq=k + 1, stamp_s=float(t), capture_stamp_s=float(t),  # offline: no publication delay
                              alpha_ip_rad=[None if not math.isfinite(a) else float(a) for a in row],
                              confidence=[0.0 if not math.isfinite(a) else float(c) for a, c in zip(row, conf)],
                              source=f"file:{video.name}")
        new.append((int(log_of[k]), msg))
    images = []
    for k, data in sorted((video.jpeg or {}).items()):
        t = float(tc[k])
        if math.isfinite(t) and t >= 0:
            images.append((int(log_of[k]), int(t * 1e9), compressed_image(t, "camera", data)))
    provenance = {
        "video": str(video_path), "video_sha256": _sha256(Path(video_path)), "video_fps": f"{video.fps:g}",
        "campaign": campaign.name, "reference": reference,
        "offset_s": f"{alignment.offset_s:.6f}", "drift": f"{alignment.drift:.3e}",
        "rms_deg": f"{alignment.rms_deg:.4f}", "frames": str(len(video.t_s)), "frames_used": str(alignment.frames_used),
        "frames_declared": str(video.declared), "frames_lost": str(video.lost), "video_loss": video.loss,
        "frames_written": str(len(new)), "missing_joints": str(int(np.isnan(video.alpha_rad).sum())),
        "runner_up_offset_s": f"{alignment.runner_up_offset_s:.6f}", "runner_up_rms_deg": f"{alignment.runner_up_rms_deg:.4f}",
        "replaced_camera_messages": str(replaced), "images": str(len(images)),
        "replaced_images": str(sum(1 for _s, c, _m in records if c.topic == IMAGE_TOPIC) if images else 0), "software": software,
        "method": "least-squares offset/drift of detected α against the reference (twin/camera/align.py)",
    }
    if out.exists():
        raise FileExistsError(errno.EEXIST, "exists already: an aligned copy is never overwritten", str(out))
    # Written beside it and linked into place only when finished: a full disk or a Ctrl-C leaves no
    # half-written MCAP under the name, and the link, unlike a rename, never replaces a file.
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        _write_copy(tmp, records, metadata, provenance, new, images, video.name)
        os.link(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return provenance


def _write_copy(path: Path, records: list, metadata: list, provenance: dict[str, str], new: list, images: list,
                video_name: str) -> None:
    """The aligned copy's MCAP (:func:`write_aligned`): ``records`` of the campaign with its camera
    messages (and images, if the video gives some) replaced by ``new`` and ``images``."""
    with open(path, "xb") as f:
        writer = Writer(f, compression=CompressionType.LZ4)
        writer.start(profile="xneck", library="xneck camera align")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        camera_schema = writer.register_schema(name=bus.schema_name(bus.CameraAlpha), encoding="jsonschema",
                                               data=bus.json_schema_bytes(bus.CameraAlpha))
        camera_channel = writer.register_channel(topic=CAMERA_TOPIC, message_encoding="json", schema_id=camera_schema,
                                                 metadata={"key": bus.CAMERA_ALPHA, "version": str(bus.schema_version(bus.CameraAlpha)),
                                                           "source": f"file:{video_name}"})
        image_channel = 0
        if images:
            image_schema = writer.register_schema(name=IMAGE_SCHEMA_NAME, encoding="jsonschema",
                                                  data=json.dumps(COMPRESSED_IMAGE_SCHEMA).encode())
            image_channel = writer.register_channel(topic=IMAGE_TOPIC, message_encoding="json", schema_id=image_schema,
                                                    metadata={"source": f"file:{video_name}"})
        # New records (log time, channel, publish time, data, sequence), merged in log-time order.
        added = sorted([(lt, camera_channel, int(m.capture_stamp_s * 1e9), bus.encode(m), m.seq) for lt, m in new]
                       + [(lt, image_channel, pt, data, i + 1) for i, (lt, pt, data) in enumerate(images)], key=lambda r: r[0])
        pending = iter(added)
        nxt = next(pending, None)

        def flush_until(log_time: float) -> None:
            nonlocal nxt
            while nxt is not None and nxt[0] <= log_time:
                lt, channel_id, publish_time, data, seq = nxt
                writer.add_message(channel_id=channel_id, log_time=lt, publish_time=publish_time, data=data, sequence=seq)
                nxt = next(pending, None)

        for schema, channel, message in records:
            # The video's α_IP replaces the recorded one; its images replace the live camera's frames.
            if channel.topic == CAMERA_TOPIC or (images and channel.topic == IMAGE_TOPIC):
                continue
            flush_until(message.log_time)
            if channel.id not in channel_ids:
                sid = 0
                if schema is not None:
                    if schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(name=schema.name, encoding=schema.encoding, data=schema.data)
                    sid = schema_ids[schema.id]
                channel_ids[channel.id] = writer.register_channel(topic=channel.topic, message_encoding=channel.message_encoding,
                                                                  schema_id=sid, metadata=dict(channel.metadata))
            writer.add_message(channel_id=channel_ids[channel.id], log_time=message.log_time, publish_time=message.publish_time,
                               data=message.data, sequence=message.sequence)
        flush_until(math.inf)
        for name, meta in metadata:
            writer.add_metadata(name, meta)
        writer.add_metadata(ALIGNMENT_METADATA, provenance)
        writer.finish()


__all__ = ["ALIGNMENT_METADATA", "RECALIBRATE_VIDEO", "Alignment", "AlignmentError", "Reference", "VideoAlpha", "align",
           "campaign_reference", "measure_video", "write_aligned"]
