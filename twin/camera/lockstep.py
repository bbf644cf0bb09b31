"""The twin's rendered camera inside the simulation: α_IP measured on frames, in lockstep.

A lockstep twin runs many times faster than a renderer, so a camera process beside it would drop
most exposures (``twin.camera.process``). Here the simulator itself calls the camera every tick
(:meth:`LockstepCamera.update`, the interface of ``twin.sim.sensors.Camera``): an exposure every
1/rate s of *simulated* time (:class:`twin.camera.source.TwinShutter`), the frame rendered from
the true α of that instant (:class:`twin.camera.render.Renderer`, 1280×720 as the prototype's
camera), measured by the robot's detector (:class:`twin.camera.detect.Detector`), and delivered
``latency_s`` later on the simulated clock. The simulation waits for it, so no frame is ever
dropped, and the result is the same for the same seed whatever the machine's load.

The renderer draws the robot being simulated (the truth's geometry); the detector measures with
the geometry the model believes (the parameter file's), as on the prototype.

Speed: an exposure is rendered on one worker thread from the moment it is taken and measured on
a second one, while the simulation runs through its latency (25 ticks at 50 ms); the frame is
collected when it is due. Each worker takes the exposures in order, so the renderer's noise and
the detector's tracking see the same sequence as without them: the result does not depend on
the timing (OpenCV releases the GIL, so on two cores most of the camera hides behind the loop).
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from twin.camera.calibration import Calibration
from twin.camera.detect import Detection, Detector
from twin.camera.render import Renderer, RenderOptions
from twin.camera.source import Exposure, TwinShutter
from twin.model.numeric import Model


class LockstepCamera:
    """α_IP frames measured on rendered images (module docstring). ``update`` returns the frames
    delivered now as (capture time s, α_IP rad with NaN for a missing joint); ``confidence`` holds
    the detector's per-joint confidence of those frames."""

    source = "twin-render"

    def __init__(self, drawn: Model, measured_L_m: float, measured_b_m: float, rate_hz: float, latency_s: float,
                 seed: int = 0, calibration: Calibration | None = None, options: RenderOptions | None = None) -> None:
        self.shutter = TwinShutter(rate_hz, latency_s, on_exposure=self._start)
        self.renderer = Renderer(drawn, calibration, options=options, seed=seed)
        self.detector = Detector(drawn.n_joints, measured_L_m, measured_b_m, calibration)
        self.confidence: list[np.ndarray] = []
        self.frames = 0
        self.missing_joints = 0
        self._workers: tuple[ThreadPoolExecutor, ThreadPoolExecutor] | None = None  # started with the first exposure
        self._jobs: deque[tuple[Exposure, Future[Detection]]] = deque()

    def _start(self, exposure: Exposure) -> None:
        if self._workers is None:
            self._workers = (ThreadPoolExecutor(1, thread_name_prefix="twin-camera-render"),
                             ThreadPoolExecutor(1, thread_name_prefix="twin-camera-detect"))
        render, detect = self._workers
        frame = render.submit(self.renderer.render, exposure.alpha_rad)
        self._jobs.append((exposure, detect.submit(lambda: self.detector.detect(frame.result()))))

    def _result(self, exposure: Exposure) -> Detection:
        while self._jobs:
            taken, job = self._jobs.popleft()
            if taken is exposure:
                return job.result()
        # Not started (cannot happen with the shutter's callback): measure it here.
        return self.detector.detect(self.renderer.render(exposure.alpha_rad))

    def close(self) -> None:
        """Stop the worker threads (they also end with the camera's last reference)."""
        if self._workers is not None:
            for worker in self._workers:
                worker.shutdown(wait=True, cancel_futures=True)
            self._workers = None
        self._jobs.clear()

    def update(self, t_s: float, alpha: np.ndarray) -> list[tuple[float, np.ndarray]]:
        """Feed the true α at simulated time ``t_s``; render and measure each exposure whose
        latency has elapsed."""
        out: list[tuple[float, np.ndarray]] = []
        self.confidence = []
        for exposure in self.shutter.feed(t_s, alpha):
            found = self._result(exposure)
            alpha_ip = np.array([np.nan if a is None else a for a in found.alpha_rad])
            self.frames += 1
            self.missing_joints += int(np.isnan(alpha_ip).sum())
            out.append((exposure.capture_s, alpha_ip))
            self.confidence.append(np.asarray(found.confidence, dtype=float))
        return out
