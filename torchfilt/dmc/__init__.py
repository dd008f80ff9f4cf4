"""DMC: step-response models, their state-space realisations, the open-loop prediction module as a
steady-state Kalman filter (Xie, Ding & Chen, Control and Decision 2016), and a DMC controller that
consumes the predictions, with the multi-priority steady-state target calculation of double-layered
DMC (Li & Ding 2015) above it.

Layer 5: imports numerics, models, filters and exceptions only.
"""

from torchfilt.dmc.benchmarks import integrating_fractionator, shell_fractionator
from torchfilt.dmc.closed_loop import ClosedLoopResult, SampledPlant, run_closed_loop
from torchfilt.dmc.controller import ControlPlan, DMCController, InfeasibleError
from torchfilt.dmc.predictor import LMGPredictor, OpenLoopPredictor, PredictorRun, steady_gain
from torchfilt.dmc.qp import QPResult, solve_qp
from torchfilt.dmc.realization import Realization, lmg_realization, realize
from torchfilt.dmc.sstc import MultiPriorityTarget, SSTCResult
from torchfilt.dmc.step_response import DiscreteModel, StepResponseModel
from torchfilt.dmc.target import FixedTarget, SteadyStateTarget, Target, TargetRow, WeightedTarget
from torchfilt.dmc.transfer import FOPDT, IPDT

__all__ = [
    "FOPDT",
    "IPDT",
    "ClosedLoopResult",
    "ControlPlan",
    "DMCController",
    "DiscreteModel",
    "FixedTarget",
    "InfeasibleError",
    "LMGPredictor",
    "MultiPriorityTarget",
    "OpenLoopPredictor",
    "PredictorRun",
    "QPResult",
    "Realization",
    "SSTCResult",
    "SampledPlant",
    "SteadyStateTarget",
    "StepResponseModel",
    "Target",
    "TargetRow",
    "WeightedTarget",
    "integrating_fractionator",
    "lmg_realization",
    "realize",
    "run_closed_loop",
    "shell_fractionator",
    "solve_qp",
    "steady_gain",
]
