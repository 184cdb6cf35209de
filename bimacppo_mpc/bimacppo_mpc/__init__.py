"""bimacppo_mpc: the low-level NMPC of BiM-ACPPO (eq. (32)-(33)). Core modules never import rclpy.

    from bimacppo_mpc import MPCConfig, make_controller
    ctrl = make_controller(MPCConfig.load(), solver="fast")   # or "ipopt"
    res = ctrl.solve(x0, x_ref, u_prev)
"""
import os

# solve_batch's parallel kernel runs on numba's OpenMP threads. OpenMP's default lets idle threads
# spin for a while after each parallel call, and two training runs sharing the cores then spin
# against each other's work: on 2 cores, two 600-episode runs side by side made 5.8 episodes/s
# each (11.6 together, less than one run alone at 19.5) spinning, and 13.8 each (27.7 together)
# with passive threads, which sleep at once; alone, passive costs about 2 % (19.2 against 19.5;
# scripts/bench_train.py --only batched --concurrent 1|2 --omp-wait active|passive). So passive
# is the default; an OMP_WAIT_POLICY the user set is kept. It must be in the environment before
# the OpenMP runtime loads, which happens at the first parallel call.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .config import MPCConfig  # noqa: E402
from .controller import (SOLVERS, FastController, IpoptController, MPCBatchResult, MPCController,
                         MPCResult, make_controller)

__version__ = "0.1.0"

__all__ = ["MPCConfig", "make_controller", "MPCResult", "MPCBatchResult", "MPCController",
           "FastController", "IpoptController", "SOLVERS"]
