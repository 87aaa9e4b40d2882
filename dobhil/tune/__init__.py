"""Robust tuning: the observer bandwidths, the identified inertia and the force gain that
give the fastest force loop whose sampled, delayed loop keeps its margins at every point of
an environment range and plant uncertainty box (``dobhil tune``).

- :mod:`problem`   the robust set, the bounds and the margins, parsed and checked
- :mod:`evaluate`  every metric for designs x points, one batch
- :mod:`optimise`  differential evolution over the batch, then the fine-grid check
- :mod:`report`    text, JSON, the tuned config
"""

from dobhil.tune.optimise import Objective, TuneResult, tune
from dobhil.tune.problem import Bounds, Margins, Range, RobustSet, Uncertainty

__all__ = ["Bounds", "Margins", "Objective", "Range", "RobustSet", "TuneResult", "Uncertainty", "tune"]
