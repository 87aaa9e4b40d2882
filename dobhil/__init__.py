"""dobhil: robust DOb/RTOb force control of servo drives over CAN.

Subpackages and modules, one concept each, one item per layer, lowest first (``LAYERS`` in
``tests/test_layers.py`` declares the order and checks every import against it: a package
imports only lower layers, and those of one layer never import each other):

- ``dobhil.errors``     the error types (exit codes)
- ``dobhil.files``, ``dobhil.data``, ``dobhil.realtime``, ``dobhil.forkserver``,
  ``dobhil.cluster``: safe output files, the shipped configs and drive profiles, thread and
  process scheduling, child processes forked from one that imported their code, work on a
  Dask cluster
- ``dobhil.config``     run/design configuration (YAML, ``--set key=value``, validation)
- ``dobhil.synthesis``  the paper's observers in state space, continuous and sampled;
  ``dobhil.drives``     drive profiles, base class and protocol implementations (codecs are pure)
- ``dobhil.analysis``   transfer functions, stability, margins, step metrics, sweeps;
  ``dobhil.emulator``   plant-plus-environment emulator, a real participant on a CAN bus;
  ``dobhil.recording``  MCAP writing (the writer process), reading, recovery, conversion
- ``dobhil.plotting``   PNG figures of what it is given (matplotlib, imported only when asked);
  ``dobhil.runtime``    the force-control loop, references, safety;
  ``dobhil.canio``      python-can plugins (the ``dobhil`` bus, MCAP as a CAN log);
  ``dobhil.live``       the Foxglove live view; ``dobhil.run_report`` the report of a recorded run;
  ``dobhil.identify``   the plant's numbers fitted to a recorded run;
  ``dobhil.tune``       robust gains over an environment range (``dobhil tune``)
- ``dobhil.replay``     a recorded run replayed through the controller;
  ``dobhil.paper``      the paper's Section IV reproduced and checked;
  ``dobhil.campaign``   Monte-Carlo campaigns of lockstep runs, as Dask tasks
- ``dobhil.cli``        the ``dobhil`` command (one module per command)
"""

from __future__ import annotations

__version__ = "0.1.0"
