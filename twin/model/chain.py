"""Positions of every bar end of N X-joints in series, in the base frame (for drawing and
forward kinematics): the 2-X paper's eq. 2 generalised from the median points to the bar ends.

Joint i's base bar is joint i−1's top bar; its frame is turned by β_i = α_1 + … + α_{i−1} and
sits at the middle of that bar. Lengths in m, α in rad, base frame as in ``twin.model.dynamics``.
"""

from __future__ import annotations

import numpy as np

from twin.model import xjoint
from twin.model.numeric import Model


def bar_ends(model: Model, alpha) -> np.ndarray:
    """World positions (m) of A, B (base bar ends) and C, D (top bar ends) of every joint.

    Returns shape (..., N, 4, 2) for ``alpha`` of shape (..., N). Springs run A–C and B–D,
    diagonals A–D and B–C.
    """
    alpha = np.asarray(alpha, dtype=float)
    tab = xjoint.jets(model.L, model.b, model.r, alpha)[..., 0]  # values only
    half = 0.5 * model.b
    local = np.stack(
        [
            np.broadcast_to([-half, 0.0], alpha.shape + (2,)),
            np.broadcast_to([half, 0.0], alpha.shape + (2,)),
            np.stack([tab[..., xjoint.C_X], tab[..., xjoint.C_Y]], axis=-1),
            np.stack([tab[..., xjoint.D_X], tab[..., xjoint.D_Y]], axis=-1),
        ],
        axis=-2,
    )  # (..., N, 4, 2) in each joint's frame
    top = np.stack([tab[..., xjoint.P_X], tab[..., xjoint.P_Y]], axis=-1)  # (..., N, 2)
    beta = np.cumsum(alpha, axis=-1) - alpha  # orientation of each joint's base bar
    cb, sb = np.cos(beta), np.sin(beta)
    rot = np.stack([np.stack([cb, -sb], -1), np.stack([sb, cb], -1)], -2)  # (..., N, 2, 2)
    top_world = np.einsum("...ij,...j->...i", rot, top)
    origin = np.cumsum(top_world, axis=-2) - top_world  # middle of each joint's base bar
    return origin[..., None, :] + np.einsum("...ij,...kj->...ki", rot, local)


def head(model: Model, alpha) -> np.ndarray:
    """Middle of the last top bar (m), shape (..., 2): the end point of 2-X paper eq. 2."""
    ends = bar_ends(model, alpha)
    return 0.5 * (ends[..., -1, 2, :] + ends[..., -1, 3, :])
