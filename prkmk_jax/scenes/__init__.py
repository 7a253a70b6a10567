from .base import AbstractScene as AbstractScene
from .forced_body import (
    ForcedParameters as ForcedParameters,
    ForcedRigidBody as ForcedRigidBody,
    HarmonicTorque as HarmonicTorque,
    harmonic_torque as harmonic_torque,
)
from .heavy_top import HeavyTop as HeavyTop, TopParameters as TopParameters
from .rigid_body import (
    PAPER_INERTIA as PAPER_INERTIA,
    PAPER_MOMENTUM as PAPER_MOMENTUM,
    PAPER_SEED as PAPER_SEED,
    FreeRigidBody as FreeRigidBody,
    SymmetricRigidBody as SymmetricRigidBody,
    elliptic_momentum as elliptic_momentum,
    angular_velocity as angular_velocity,
    attitude_and_momentum as attitude_and_momentum,
    from_attitude_and_momentum as from_attitude_and_momentum,
    random_rotation as random_rotation,
    skew_arcsinh as skew_arcsinh,
    symmetric_initial_state as symmetric_initial_state,
    symmetric_rigid_body as symmetric_rigid_body,
    unreduced_rigid_body as unreduced_rigid_body,
)
