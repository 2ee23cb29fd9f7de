"""jaxquat: differentiable quaternions and rigid-body rotation in JAX.

Conventions: quaternions are arrays shaped ``(..., 4)``, scalar first
``(w, x, y, z)``; Hamilton product (``i j = k``); active rotation
``v' = q v q*``; rotation matrices act on column vectors; leading axes are batch
axes and broadcast. Importing jaxquat changes no global JAX setting.

Each module's ``__all__`` is its public surface; the package re-exports them all.
"""

from . import (
    algebra, conversions, determination, dynamics, elliptic, euler, fixed_step, geometry, inertia, interior_point, interpolate,
    kinematics, lie,
    lie_solvers, mekf as _mekf_module, models, optimal_control, rigid_body, simulate as _simulate_module, skew, spline, splitting, tangent, time_optimal, torque_free,
    torques, ukf as _ukf_module,
)
from .algebra import *  # noqa: F401,F403
from .conversions import *  # noqa: F401,F403
from .determination import *  # noqa: F401,F403
from .dynamics import *  # noqa: F401,F403
from .elliptic import *  # noqa: F401,F403
from .euler import *  # noqa: F401,F403
from .geometry import *  # noqa: F401,F403
from .inertia import *  # noqa: F401,F403
from .fixed_step import *  # noqa: F401,F403
from .interior_point import *  # noqa: F401,F403
from .interpolate import *  # noqa: F401,F403
from .kinematics import *  # noqa: F401,F403
from .lie import *  # noqa: F401,F403
from .lie_solvers import *  # noqa: F401,F403
from .mekf import *  # noqa: F401,F403
from .models import *  # noqa: F401,F403
from .optimal_control import *  # noqa: F401,F403
from .rigid_body import *  # noqa: F401,F403
from .simulate import *  # noqa: F401,F403
from .skew import *  # noqa: F401,F403
from .spline import *  # noqa: F401,F403
from .splitting import *  # noqa: F401,F403
from .tangent import *  # noqa: F401,F403
from .time_optimal import *  # noqa: F401,F403
from .torque_free import *  # noqa: F401,F403
from .torques import *  # noqa: F401,F403
from .ukf import *  # noqa: F401,F403

__version__ = "0.1.0"

__all__ = [
    *algebra.__all__,
    *conversions.__all__,
    *euler.__all__,
    *geometry.__all__,
    *interpolate.__all__,
    *skew.__all__,
    *kinematics.__all__,
    *inertia.__all__,
    *dynamics.__all__,
    *torques.__all__,
    *lie.__all__,
    *tangent.__all__,
    *spline.__all__,
    *elliptic.__all__,
    *torque_free.__all__,
    *rigid_body.__all__,
    *models.__all__,
    *lie_solvers.__all__,
    *splitting.__all__,
    *fixed_step.__all__,
    *_simulate_module.__all__,
    *interior_point.__all__,
    *optimal_control.__all__,
    *time_optimal.__all__,
    *determination.__all__,
    *_mekf_module.__all__,
    *_ukf_module.__all__,
]
