"""Robot motion and relative-measurement models (the paper's eqs. (2) and (3))."""

from resloc.models.measurement import (
    measurement_noise,
    range_bearing,
    range_bearing_jacobians,
)
from resloc.models.motion import (
    process_noise,
    unicycle_input_jacobian,
    unicycle_state_jacobian,
    unicycle_step,
)

__all__ = [
    "measurement_noise",
    "process_noise",
    "range_bearing",
    "range_bearing_jacobians",
    "unicycle_input_jacobian",
    "unicycle_state_jacobian",
    "unicycle_step",
]
