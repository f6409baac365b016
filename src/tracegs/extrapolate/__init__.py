"""What happens after training: the extrapolation policy (the gsplat split of policy and mechanics).

``calibrate(model, t_max, settings, data)`` chooses, on the training images, the post-training state
(``ExtrapolationState``: the handover's freeze threshold, the Gaussians no camera saw, the free bodies,
the parts with their identified models) and returns the trained run as a ``Predictor``, which turns any
time into Gaussians and any camera at that time into an image; the run folder stores the state
(``run.py``), and ``run.load_run`` builds the same ``Predictor`` from it. ``still_codes`` says which
Gaussians hold still after the handover and why.
"""

from .calibrate import calibrate, has_policy
from .predictor import MAX_TIME_FACTOR, MOTIONS, Predictor, check_time
from .settings import ExtrapolationConfig
from .state import ExtrapolationState
from .still import REASONS, still_codes

__all__ = [
    "MAX_TIME_FACTOR",
    "MOTIONS",
    "REASONS",
    "ExtrapolationConfig",
    "ExtrapolationState",
    "Predictor",
    "calibrate",
    "check_time",
    "has_policy",
    "still_codes",
]
