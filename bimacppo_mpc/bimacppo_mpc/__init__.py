"""bimacppo_mpc: the low-level NMPC of BiM-ACPPO (eq. (32)-(33)). Core modules never import rclpy.

    from bimacppo_mpc import MPCConfig, make_controller
    ctrl = make_controller(MPCConfig.load(), solver="fast")   # or "ipopt"
    res = ctrl.solve(x0, x_ref, u_prev)
"""
import bimacppo_common  # noqa: F401  (first: idle OpenMP threads sleep; bimacppo_common says why)

from .config import MPCConfig  # noqa: E402
from .controller import (SOLVERS, FastController, IpoptController, MPCBatchResult, MPCController,
                         MPCResult, make_controller)

__version__ = "0.1.0"

__all__ = ["MPCConfig", "make_controller", "MPCResult", "MPCBatchResult", "MPCController",
           "FastController", "IpoptController", "SOLVERS"]
