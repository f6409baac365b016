"""What happens after training: the extrapolation policy (the gsplat split of policy and mechanics).

``calibrate(model, t_max)`` chooses, on the training images, the post-training state
(``ExtrapolationState``: the handover's freeze threshold, the Gaussians no camera saw, the free bodies,
the joint parts with their force laws);
the run folder stores it (``run.py``). ``gaussians_at(model, state, t)`` turns a model and its state into
Gaussians at any time t. ``still_codes`` says which Gaussians hold still after the handover and why.
"""

from .calibrate import calibrate, has_policy
from .future import gaussians_at, handover_time, physics_from
from .state import ExtrapolationState
from .still import REASONS, still_codes

__all__ = [
    "REASONS",
    "ExtrapolationState",
    "calibrate",
    "gaussians_at",
    "handover_time",
    "has_policy",
    "physics_from",
    "still_codes",
]
