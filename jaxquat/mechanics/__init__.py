"""Rigid-body mechanics: kinematics in the body and space frames, inertia, Euler's equations and
the Euler-parameter equations of motion, torques, the vector fields (rigid body, quadrotor,
reaction-wheel spacecraft), the exact torque-free motion and its elliptic functions.

Every public name is re-exported by ``jaxquat`` (use ``jaxquat.name``); the modules here are
the layer's files (``docs/architecture.md`` has the map)."""
