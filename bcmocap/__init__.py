"""bcmocap: differentiable articulated bundle adjustment in JAX.

Motion capture from body-mounted cameras: a skeleton whose segments carry cameras is fitted to what
those cameras saw of a static scene (Shiratori et al., SIGGRAPH 2011), with a Levenberg–Marquardt
solver that exploits the problem's structure.

Importing the package turns on float64 in JAX: geometry and solvers need it.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
