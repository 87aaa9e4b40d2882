"""Plant-plus-environment emulator: a real participant on a python-can bus.

:mod:`dobhil.drives.emulated` holds the emulated-drive base (bus, timing modes,
cyclic frames) and the :class:`PlantLike` interface of the injected dynamics;
each protocol's ``emulator`` module (``dobhil/drives/<protocol>/emulator.py``, found through
its ``DriveProtocol.emulator_class``) keeps the drive's state machine.
"""
