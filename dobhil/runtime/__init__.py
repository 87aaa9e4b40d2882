"""The runtime: the force controller executed per sample and the reference signals.

- :mod:`dobhil.runtime.controller`  :class:`ForceController`, the sampled DOb/RTOb law
- :mod:`dobhil.runtime.references`  :func:`make_reference`, the tau_int^ref signals
"""

from __future__ import annotations
