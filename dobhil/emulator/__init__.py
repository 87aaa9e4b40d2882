"""Plant-plus-environment emulator: a real participant on a python-can bus.

:mod:`dobhil.drives.emulated` holds the emulated-drive base (bus, timing modes,
cyclic frames) and the :class:`PlantLike` interface of the injected dynamics;
one module per protocol (:mod:`dobhil.drives.odrive.emulator`) keeps the drive's state machine.
"""
