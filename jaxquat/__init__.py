"""jaxquat: differentiable quaternions and rigid-body rotation in JAX.

Conventions: quaternions are arrays shaped ``(..., 4)``, scalar first
``(w, x, y, z)``; Hamilton product (``i j = k``); active rotation
``v' = q v q*``; rotation matrices act on column vectors; leading axes are batch
axes and broadcast. Importing jaxquat changes no global JAX setting.

Each module's ``__all__`` is its public surface; the package re-exports them all, by name: the
imports are listed in ``__init__.pyi`` (for type checkers as well) and run on first use of a
name (``lazy_loader``), so ``import jaxquat`` imports none of jaxquat's modules, nor diffrax,
equinox, optax or optimistix, until one is used: the rotations without the integrators cost
no diffrax import. ``EAGER_IMPORT=1`` imports everything at once (``lazy_loader``'s switch).
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)

__version__ = "0.1.0"
