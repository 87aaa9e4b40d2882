"""dobhil: robust DOb/RTOb force control of servo drives over CAN.

Subpackages, one concept each:

- ``dobhil.config``     run/design configuration (YAML, ``--set key=value``, validation)
- ``dobhil.synthesis``  the paper's observers in state space, continuous and sampled
- ``dobhil.analysis``   transfer functions, stability, margins, step metrics, sweeps
- ``dobhil.plotting``   PNG figures (matplotlib, imported only when asked)
- ``dobhil.drives``     drive base class and protocol implementations (codecs are pure)
- ``dobhil.emulator``   plant-plus-environment emulator, a real participant on a CAN bus
- ``dobhil.runtime``    the force-control loop, references, safety
- ``dobhil.recording``  MCAP recording, replay support, log tools
- ``dobhil.cli``        the ``dobhil`` command
"""

from __future__ import annotations

__version__ = "0.1.0"
