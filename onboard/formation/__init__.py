"""Formation control on board: the decentralised formation MPC, slot assignment and failsafe decisions.

Import the parts from their modules (``onboard.formation.mpc``, ``.slots``, ``.failsafe``, ``.source``);
``source`` imports the agent's ``onboard.setpoint`` and is not loaded here.
"""

from onboard.formation.failsafe import FailsafeAction, FailsafeConfig, FailsafeDecision, FailsafeInputs, FormationSupervisor, decide
from onboard.formation.mpc import Cylinder, FormationMPC, MpcConfig, MpcError, MpcResult, SharedPlan
from onboard.formation.slots import assign_slot_angles

__all__ = [
    "Cylinder",
    "FailsafeAction",
    "FailsafeConfig",
    "FailsafeDecision",
    "FailsafeInputs",
    "FormationMPC",
    "FormationSupervisor",
    "MpcConfig",
    "MpcError",
    "MpcResult",
    "SharedPlan",
    "assign_slot_angles",
    "decide",
]
