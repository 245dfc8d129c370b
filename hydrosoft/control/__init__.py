"""Control: the CEM + gradient-descent MPC solver (Algorithm 1) and differentiable cost terms."""
from hydrosoft.control.cem_gd import CemGd, CemGdConfig, PlanResult, device_unavailable
from hydrosoft.control.costs import effort_cost, hinge_cost, orientation_error, pose_cost, position_error
from hydrosoft.control.worker_processes import WorkerError, WorkerProcesses

__all__ = [
    "CemGd",
    "CemGdConfig",
    "PlanResult",
    "WorkerError",
    "WorkerProcesses",
    "device_unavailable",
    "effort_cost",
    "hinge_cost",
    "orientation_error",
    "pose_cost",
    "position_error",
]
