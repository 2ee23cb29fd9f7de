"""The public names of jaxquat, for type checkers and for the lazy loading in ``__init__.py``.

Each module's ``__all__`` is its public surface; the package re-exports them all, by name
(``name as name``, so type checkers see each re-export). ``__init__.py`` reads the imports
below (``lazy_loader.attach_stub``) and imports a module on the first use of one of its names.
"""

from .rotations.algebra import (
    multiply as multiply,
    conjugate as conjugate,
    inverse as inverse,
    norm as norm,
    normalize as normalize,
    identity as identity,
    random as random,
    exp as exp,
    log as log,
    power as power,
    left_matrix as left_matrix,
    right_matrix as right_matrix,
    rotate as rotate,
    canonicalize as canonicalize,
)
from .rotations.conversions import (
    to_matrix as to_matrix,
    from_matrix as from_matrix,
    to_rotvec as to_rotvec,
    from_rotvec as from_rotvec,
    to_axis_angle as to_axis_angle,
    from_axis_angle as from_axis_angle,
    to_mrp as to_mrp,
    from_mrp as from_mrp,
)
from .rotations.determination import (
    triad as triad,
    quest as quest,
    align_vectors as align_vectors,
    attitude_covariance as attitude_covariance,
)
from .rotations.euler_angles import (
    from_euler as from_euler,
    to_euler as to_euler,
)
from .rotations.geometry import (
    angle as angle,
    angle_between as angle_between,
    mean as mean,
)
from .rotations.skew import (
    hat as hat,
    vee as vee,
)
from .manifold.interpolate import (
    slerp as slerp,
    squad as squad,
    squad_control_points as squad_control_points,
    squad_segment as squad_segment,
)
from .manifold.lie import (
    plus as plus,
    minus as minus,
    right_jacobian as right_jacobian,
    right_jacobian_inverse as right_jacobian_inverse,
    left_jacobian as left_jacobian,
    left_jacobian_inverse as left_jacobian_inverse,
    adjoint as adjoint,
)
from .manifold.spline import (
    RotationSpline as RotationSpline,
)
from .manifold.tangent import (
    tangent_gradient as tangent_gradient,
    tangent_gradients as tangent_gradients,
    tangent_optimizer as tangent_optimizer,
    apply_tangent_updates as apply_tangent_updates,
)
from .mechanics.dynamics import (
    angular_momentum as angular_momentum,
    kinetic_energy as kinetic_energy,
    angular_acceleration as angular_acceleration,
    inverse_dynamics as inverse_dynamics,
    euler_parameter_acceleration as euler_parameter_acceleration,
    euler_parameter_torque as euler_parameter_torque,
    euler_parameter_mass_matrix as euler_parameter_mass_matrix,
    euler_parameter_augmented_system as euler_parameter_augmented_system,
    norm_constraint_multiplier as norm_constraint_multiplier,
    generalized_force as generalized_force,
    torque_from_generalized_force as torque_from_generalized_force,
)
from .mechanics.elliptic import (
    ellipj as ellipj,
    ellipk as ellipk,
    elliprf as elliprf,
    elliprj as elliprj,
)
from .mechanics.inertia import (
    inertia_from_points as inertia_from_points,
    rotate_inertia as rotate_inertia,
    inertia_rate as inertia_rate,
    quaternion_inertia as quaternion_inertia,
    is_valid_inertia as is_valid_inertia,
    check_inertia as check_inertia,
    principal_axes as principal_axes,
)
from .mechanics.kinematics import (
    rate_matrix as rate_matrix,
    qdot_from_omega as qdot_from_omega,
    omega_from_qdot as omega_from_qdot,
    qddot_from_alpha as qddot_from_alpha,
    alpha_from_qddot as alpha_from_qddot,
    matrix_rate as matrix_rate,
    matrix_acceleration as matrix_acceleration,
    point_velocity as point_velocity,
    point_acceleration as point_acceleration,
)
from .mechanics.models import (
    Quadrotor as Quadrotor,
    ReactionWheelSpacecraft as ReactionWheelSpacecraft,
)
from .mechanics.rigid_body import (
    RigidBody as RigidBody,
    EulerParameterBody as EulerParameterBody,
    invariants as invariants,
)
from .mechanics.torque_free import (
    euler_poinsot as euler_poinsot,
    polhode_period as polhode_period,
)
from .mechanics.torques import (
    as_body_torque as as_body_torque,
    gravity_gradient_torque as gravity_gradient_torque,
    circular_orbit_gravity_gradient as circular_orbit_gravity_gradient,
)
from .integration.fixed_step import (
    solve_fixed_steps as solve_fixed_steps,
)
from .integration.lie_solvers import (
    AbstractLeafInterpolation as AbstractLeafInterpolation,
    SlerpInterpolation as SlerpInterpolation,
    LocalPolynomialInterpolation as LocalPolynomialInterpolation,
    BodyRateTerm as BodyRateTerm,
    AbstractLieSolver as AbstractLieSolver,
    AbstractRKMK as AbstractRKMK,
    LieEuler as LieEuler,
    RKMK4 as RKMK4,
    RKMK45 as RKMK45,
    RKMKTsit5 as RKMKTsit5,
    RKMK8 as RKMK8,
)
from .integration.simulation import (
    Simulation as Simulation,
    simulate as simulate,
)
from ._threads import (
    cpu_compiler_options as cpu_compiler_options,
)
from .integration.splitting import (
    AbstractSplitting as AbstractSplitting,
    RigidBodySplit as RigidBodySplit,
    RigidBodySplit4 as RigidBodySplit4,
    EulerPoinsotSplit as EulerPoinsotSplit,
    EulerPoinsotSplit4 as EulerPoinsotSplit4,
)
from .control.interior_point import (
    ShootingProblem as ShootingProblem,
    ShootingSolution as ShootingSolution,
    solve_shooting as solve_shooting,
)
from .control.transcription import (
    ConstrainedReorientation as ConstrainedReorientation,
)
from .control.controlled_model import (
    ControlledModel as ControlledModel,
)
from .control.optimal_control import (
    ReactionWheels as ReactionWheels,
    minimum_energy_reorientation as minimum_energy_reorientation,
    minimum_fuel_reorientation as minimum_fuel_reorientation,
    constrained_minimum_time as constrained_minimum_time,
    optimal_reorientation as optimal_reorientation,
    refine_mesh as refine_mesh,
    align_mesh as align_mesh,
    switch_times as switch_times,
)
from .control.time_optimal import (
    Reorientation as Reorientation,
    minimum_time_reorientation as minimum_time_reorientation,
)
from .estimation.mekf import (
    FilterState as FilterState,
    FilterUpdate as FilterUpdate,
    FilterResult as FilterResult,
    mekf_init as mekf_init,
    mekf_predict as mekf_predict,
    mekf_update as mekf_update,
    mekf_update_quaternion as mekf_update_quaternion,
    mekf as mekf,
)
from .estimation.ukf import (
    ukf_predict as ukf_predict,
    ukf_update as ukf_update,
    ukf_update_quaternion as ukf_update_quaternion,
    ukf as ukf,
)

__version__: str

# In the order of docs/architecture.md's layers; tests/test_docs.py checks that it is the union of
# the modules' own __all__ (each module's __all__ is its public surface).
__all__ = [
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
    "angle",
    "angle_between",
    "mean",
    "align_vectors",
    "random",
    "slerp",
    "squad",
    "squad_control_points",
    "squad_segment",
    "hat",
    "vee",
    "rate_matrix",
    "qdot_from_omega",
    "omega_from_qdot",
    "qddot_from_alpha",
    "alpha_from_qddot",
    "matrix_rate",
    "matrix_acceleration",
    "point_velocity",
    "point_acceleration",
    "inertia_from_points",
    "rotate_inertia",
    "inertia_rate",
    "quaternion_inertia",
    "is_valid_inertia",
    "check_inertia",
    "principal_axes",
    "angular_momentum",
    "kinetic_energy",
    "angular_acceleration",
    "inverse_dynamics",
    "euler_parameter_acceleration",
    "euler_parameter_torque",
    "euler_parameter_mass_matrix",
    "euler_parameter_augmented_system",
    "norm_constraint_multiplier",
    "generalized_force",
    "torque_from_generalized_force",
    "as_body_torque",
    "gravity_gradient_torque",
    "circular_orbit_gravity_gradient",
    "plus",
    "minus",
    "right_jacobian",
    "right_jacobian_inverse",
    "left_jacobian",
    "left_jacobian_inverse",
    "adjoint",
    "tangent_gradient",
    "tangent_gradients",
    "tangent_optimizer",
    "apply_tangent_updates",
    "RotationSpline",
    "ellipj",
    "ellipk",
    "elliprf",
    "elliprj",
    "euler_poinsot",
    "polhode_period",
    "RigidBody",
    "EulerParameterBody",
    "invariants",
    "Quadrotor",
    "ReactionWheelSpacecraft",
    "AbstractLeafInterpolation",
    "SlerpInterpolation",
    "LocalPolynomialInterpolation",
    "BodyRateTerm",
    "AbstractLieSolver",
    "AbstractRKMK",
    "LieEuler",
    "RKMK4",
    "RKMK45",
    "RKMKTsit5",
    "RKMK8",
    "AbstractSplitting",
    "RigidBodySplit",
    "RigidBodySplit4",
    "EulerPoinsotSplit",
    "EulerPoinsotSplit4",
    "solve_fixed_steps",
    "Simulation",
    "simulate",
    "cpu_compiler_options",
    "ShootingProblem",
    "ShootingSolution",
    "solve_shooting",
    "ConstrainedReorientation",
    "ControlledModel",
    "ReactionWheels",
    "minimum_energy_reorientation",
    "minimum_fuel_reorientation",
    "optimal_reorientation",
    "refine_mesh",
    "align_mesh",
    "switch_times",
    "constrained_minimum_time",
    "Reorientation",
    "minimum_time_reorientation",
    "triad",
    "quest",
    "attitude_covariance",
    "FilterState",
    "FilterUpdate",
    "FilterResult",
    "mekf_init",
    "mekf_predict",
    "mekf_update",
    "mekf_update_quaternion",
    "mekf",
    "ukf_predict",
    "ukf_update",
    "ukf_update_quaternion",
    "ukf",
]
