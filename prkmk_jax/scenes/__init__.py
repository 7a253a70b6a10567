from .base import AbstractScene as AbstractScene
from .forced_body import (
    ForcedParameters as ForcedParameters,
)
from .forced_body import (
    ForcedRigidBody as ForcedRigidBody,
)
from .forced_body import (
    HarmonicTorque as HarmonicTorque,
)
from .forced_body import (
    harmonic_torque as harmonic_torque,
)
from .heavy_top import HeavyTop as HeavyTop
from .heavy_top import SphericalTop as SphericalTop
from .heavy_top import TopParameters as TopParameters
from .rigid_body import (
    PAPER_INERTIA as PAPER_INERTIA,
)
from .rigid_body import (
    PAPER_MOMENTUM as PAPER_MOMENTUM,
)
from .rigid_body import (
    PAPER_SEED as PAPER_SEED,
)
from .rigid_body import (
    FreeRigidBody as FreeRigidBody,
)
from .rigid_body import (
    SymmetricRigidBody as SymmetricRigidBody,
)
from .rigid_body import (
    angular_velocity as angular_velocity,
)
from .rigid_body import (
    attitude_and_momentum as attitude_and_momentum,
)
from .rigid_body import (
    elliptic_momentum as elliptic_momentum,
)
from .rigid_body import (
    from_attitude_and_momentum as from_attitude_and_momentum,
)
from .rigid_body import (
    random_rotation as random_rotation,
)
from .rigid_body import (
    skew_arcsinh as skew_arcsinh,
)
from .rigid_body import (
    symmetric_initial_state as symmetric_initial_state,
)
from .rigid_body import (
    symmetric_rigid_body as symmetric_rigid_body,
)
from .rigid_body import (
    unreduced_rigid_body as unreduced_rigid_body,
)
