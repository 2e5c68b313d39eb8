"""A road-design prior corrected by a measurement (``sim.spec.RoadDesign`` gives each prior's mean and spread).

Why: the agent's road-design numbers are what a driver assumes of a road it has not measured. Where perception
measures the same quantity, the two are weighed by how sure each is (inverse variances, the one-dimensional
Kalman update); a prior with no spread is the design itself and stays as it is, so the classic design's behaviour
does not move with measurement noise.
"""

from __future__ import annotations

from towndrive.sim.spec import ROAD


def fused(prior: float, prior_sd: float, measured: float | None, measured_sd: float) -> float:
    """The prior corrected by the measurement, each weighted by its inverse variance; a prior with no spread is
    exact, and no measurement leaves the prior."""
    if measured is None or prior_sd <= 0.0:
        return prior
    wp, wm = 1.0 / prior_sd ** 2, 1.0 / max(measured_sd, 1e-3) ** 2
    return (wp * prior + wm * measured) / (wp + wm)


def junction_widening_m(setback_m: float) -> float:
    """How much wider a junction whose stop bars stand ``setback_m`` from its centre is than the classic design's,
    along the approach (both sides): the agent's distances inside a junction are configured for the classic one."""
    return 2.0 * (setback_m - ROAD.stop_line_setback_m)
