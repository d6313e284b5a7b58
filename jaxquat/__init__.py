"""jaxquat: differentiable JAX quaternions and rigid-body orientation integrators.

Quaternions are `(..., 4)` arrays ordered (w, x, y, z), Hamilton product, active rotations
v' = q v q⁻¹; `multiply(q2, q1)` applies q1 first. Angular velocities are `(..., 3)` in rad/s,
world frame unless `frame="body"`.
"""

import importlib.metadata as _metadata
import sys as _sys

if _sys.argv[:1] == ["-m"]:  # `python -m jaxquat`: Python sets argv[0] to "-m" while it loads us
    from ._interrupt import quiet_while_loading as _quiet_while_loading

    _quiet_while_loading()

# Algebra
from ._algebra import (
    conjugate as conjugate,
    dot as dot,
    exp as exp,
    from_vector as from_vector,
    identity as identity,
    inverse as inverse,
    log as log,
    multiply as multiply,
    norm as norm,
    normalize as normalize,
    vector_part as vector_part,
)

# Dynamics
from ._dynamics import (
    angular_momentum as angular_momentum,
    center_of_mass as center_of_mass,
    euler_equations as euler_equations,
    inertia_tensor as inertia_tensor,
    kinetic_energy as kinetic_energy,
    principal_axes as principal_axes,
    rigid_body_vector_field as rigid_body_vector_field,
    simulate_deformable_body as simulate_deformable_body,
    simulate_rigid_body as simulate_rigid_body,
)

# Ensembles
from ._ensemble import (
    EnsembleResult as EnsembleResult,
    body_sharding as body_sharding,
    load_ensemble as load_ensemble,
    simulate_ensemble as simulate_ensemble,
)

# Fitting
from ._fitting import (
    AngularVelocityCurve as AngularVelocityCurve,
    AngularVelocityFit as AngularVelocityFit,
    RigidBodyFit as RigidBodyFit,
    fit_angular_velocity as fit_angular_velocity,
    fit_rigid_body as fit_rigid_body,
)

# Geometry
from ._geometry import (
    angle_between as angle_between,
    canonicalize as canonicalize,
    check_unit as check_unit,
    mean as mean,
    random as random,
    slerp as slerp,
    squad as squad,
    squad_control_points as squad_control_points,
)

# Fixed-step integration
from ._integrate import integrate as integrate, sampled as sampled

# Kinematics
from ._kinematics import (
    angular_velocity as angular_velocity,
    corrected_rate as corrected_rate,
    rate as rate,
    step as step,
)

# Rotations
from ._rotation import (
    from_axis_angle as from_axis_angle,
    from_euler as from_euler,
    from_matrix as from_matrix,
    from_rotvec as from_rotvec,
    from_two_vectors as from_two_vectors,
    from_xyzw as from_xyzw,
    rotate as rotate,
    to_axis_angle as to_axis_angle,
    to_euler as to_euler,
    to_matrix as to_matrix,
    to_rotvec as to_rotvec,
    to_xyzw as to_xyzw,
)

# diffrax vector fields and solvers
from ._solvers import (
    CF4 as CF4,
    RKMK45 as RKMK45,
    ExpMidpoint as ExpMidpoint,
    LieCubicInterpolation as LieCubicInterpolation,
    LieEuler as LieEuler,
    LiePolynomialInterpolation as LiePolynomialInterpolation,
    Magnus4 as Magnus4,
    Magnus6 as Magnus6,
    Magnus8 as Magnus8,
    NormalizedEuler as NormalizedEuler,
    corrected_vector_field as corrected_vector_field,
    kinematic_vector_field as kinematic_vector_field,
)

# The public names: everything imported above (for `from jaxquat import *` and introspection).
__all__ = sorted(name for name in dir() if not name.startswith("_"))

try:
    __version__ = _metadata.version("jaxquat")
except _metadata.PackageNotFoundError:  # running from a source tree without install
    __version__ = "0+unknown"

if _sys.argv[:1] == ["-m"]:
    from ._interrupt import loaded as _loaded

    _loaded()
