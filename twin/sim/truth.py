"""What the twin simulates where the robot differs from the model the controller runs.

The parameter file is the *model*: the paper's identified values, and c_a = 3000 N·s/m for every
cable, which the 3-X paper (§5.3) chose "in order to damp the elongation in our model" — a choice
for its simulator and its eq. 58, not a measurement. Two truths:

``"model"``
    The twin simulates the parameter file exactly (the paper's simulator, §5.6). Controller and
    twin then share one model; campaigns measure the control law, not the model's errors.

``"robot"``
    The parameter file, but with the small cable damping of a real line, :data:`C_A_ROBOT`. The
    paper found the damping "not identifiable" (Tables 1-2: relative σ 15-94 %; its estimates
    change sign and differ between the two tables by a factor of 2, so they measure model error
    rather than damping). A braided polymer line has a loss factor η of order 0.1; at the
    motor-cable mode (equivalent mass m = I_a·(R/r_d)² ≈ 18 kg, stiffness k + λ·t ≈ 5-8 kN/m) that
    is a viscous c = η·√(k·m) ≈ 30-40 N·s/m. The model keeps 3000 N·s/m (a badly identified
    parameter is never used silently), so the controller's eq. 58 carries the same mismatch it has
    on the prototype. docs/identification.md shows what this changes and how sensitive it is.
"""

from __future__ import annotations

from typing import Literal

import msgspec

from twin.model.params import Params

TruthName = Literal["model", "robot"]  # which parameters the twin integrates (not the bus message bridge.bus.Truth)
TRUTHS: tuple[str, ...] = ("model", "robot")

C_A_ROBOT = 40.0  # N·s/m, cable damping of the simulated robot (all cables, both cable models)


def truth_params(params: Params, truth: TruthName = "model") -> Params:
    """The parameter set the twin integrates for ``truth`` (see the module docstring)."""
    if truth == "model":
        return params
    if truth != "robot":
        raise ValueError(f"truth must be one of {', '.join(TRUTHS)}, got {truth!r}")
    c = params.cables
    damping = (C_A_ROBOT,) * params.n_cables
    cables = msgspec.structs.replace(
        c,
        linear=msgspec.structs.replace(c.linear, c_a=damping),
        variable=msgspec.structs.replace(c.variable, c_a=damping),
    )
    return msgspec.structs.replace(params, name=f"{params.name} (robot truth)", cables=cables)
