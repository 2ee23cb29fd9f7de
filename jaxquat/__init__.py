"""jaxquat: differentiable quaternions and rigid-body rotation in JAX.

Conventions: quaternions are arrays shaped ``(..., 4)``, scalar first
``(w, x, y, z)``; Hamilton product (``i j = k``); active rotation
``v' = q v q*``; rotation matrices act on column vectors; leading axes are batch
axes and broadcast. Importing jaxquat changes no global JAX setting.
"""

from .algebra import (
    canonicalize,
    conjugate,
    exp,
    identity,
    inverse,
    left_matrix,
    log,
    multiply,
    norm,
    normalize,
    power,
    right_matrix,
    rotate,
)
from .conversions import (
    from_axis_angle,
    from_matrix,
    from_mrp,
    from_rotvec,
    to_axis_angle,
    to_matrix,
    to_mrp,
    to_rotvec,
)
from .euler import from_euler, to_euler
from .geometry import align_vectors, angle, angle_between, mean, random
from .interpolate import slerp

__version__ = "0.1.0"

__all__ = [
    # algebra
    "multiply",
    "conjugate",
    "inverse",
    "norm",
    "normalize",
    "identity",
    "exp",
    "log",
    "power",
    "left_matrix",
    "right_matrix",
    "rotate",
    "canonicalize",
    # conversions
    "to_matrix",
    "from_matrix",
    "to_rotvec",
    "from_rotvec",
    "to_axis_angle",
    "from_axis_angle",
    "to_mrp",
    "from_mrp",
    "from_euler",
    "to_euler",
    # geometry and statistics
    "angle",
    "angle_between",
    "mean",
    "align_vectors",
    "random",
    # interpolation
    "slerp",
]
