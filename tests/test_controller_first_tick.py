"""The controller's first ticks cost what every tick costs (issue 21): the warm-up before the loop
loads every compiled kernel a tick may call, whatever the drives' state of the first states.
Seen on the bus: a first state with the drives inactive loaded the estimation kernel from numba's
cache inside the tick (45 ms, a deadline miss at every start)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# A fresh interpreter: in the test process other tests may have loaded the kernels already.
SCRIPT = """
import json
import numpy as np
from numba.core import dispatcher
from controller.laws import LawConfig
from controller.service import CampaignService
from controller.trajectory import Trajectory
from twin.model.params import load_params

loaded = []
original = dispatcher.Dispatcher._compile_for_args
def recording(self, *args, **kws):
    loaded.append(self.py_func.__qualname__)
    return original(self, *args, **kws)
dispatcher.Dispatcher._compile_for_args = recording

params = load_params()
svc = CampaignService(params, LawConfig(law=2), service=False, settle_s=1.0, campaign_id="c", kind="control")
svc.warm_up()
warmed = list(loaded)
loaded.clear()
theta, f = np.full(params.n_cables, 0.01), np.full(params.n_cables, 10.0)
svc.initialise(theta)
svc.begin(Trajectory.from_degrees([[0, 0, 0], [10, 5, 5]], durations_s=1.0, name="t"), 0.0)
for k, drive in enumerate(["inactive", "disabled", "hold", "active", "active"]):
    svc.control(theta, 0.002 * k, drive, f)
svc.stale("stale state", 1.0)
svc.control(theta, 0.012, "active", f)
print(json.dumps({"warmed": warmed, "in_ticks": loaded}))
"""


def test_no_kernel_is_loaded_inside_a_tick_after_the_warm_up():
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["warmed"], got  # the hook sees the kernels (else this test could not fail)
    assert got["in_ticks"] == [], got
