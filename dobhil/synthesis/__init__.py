"""The paper's synthesis in state space, batched over designs.

- :mod:`params`      numeric parameters and structural choices
- :mod:`models`      servo/plant models and torque models, observer gain rule
- :mod:`observers`   the auxiliary-variable observers (Eqs. 10, 16, derived afresh)
- :mod:`controller`  the controller, continuous and sampled (:func:`sampled_controller`
                     is the one source of the matrices the runtime executes)
- :mod:`loop`        the closed loop with plant and environment (Eqs. 18-20)
"""

from dobhil.synthesis.controller import (ControllerSS, continuous_controller, discretize_delayed,
                                         sampled_controller)
from dobhil.synthesis.loop import INPUTS, OUTPUTS, LoopSS, loop, sampled_plant
from dobhil.synthesis.params import Params, params_from_config

__all__ = ["INPUTS", "OUTPUTS", "ControllerSS", "LoopSS", "Params", "continuous_controller",
           "discretize_delayed", "loop", "params_from_config", "sampled_controller",
           "sampled_plant"]
