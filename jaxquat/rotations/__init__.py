"""Quaternions and rotations: the algebra, conversions to and from matrices, rotation vectors,
axis-angle, MRPs and Euler angles, angles and means, attitude determination (TRIAD, QUEST,
Wahba's problem), hat/vee.

Every public name is re-exported by ``jaxquat`` (use ``jaxquat.name``); the modules here are
the layer's files (``docs/architecture.md`` has the map)."""
