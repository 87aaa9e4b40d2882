"""python-can plugins: dobhil recordings and the emulated drive in any python-can program.

Registered as entry points (``pyproject.toml``) that python-can 4.x discovers by itself:

- ``can.io.message_reader`` ``.mcap`` -> :class:`~dobhil.canio.mcap_reader.McapReader`:
  ``can.LogReader("run.mcap")`` yields a recording's ``/can/rx`` and ``/can/tx`` frames;
- ``can.io.message_writer`` ``.mcap`` -> :class:`~dobhil.canio.mcap_writer.McapWriter`:
  ``can.Logger("x.mcap")`` (so ``can.logger``, ``can.logconvert``) writes the same topics
  and JSON schemas as a ``dobhil run --log``;
- ``can.interface`` ``dobhil`` -> :class:`~dobhil.canio.bus.DobhilBus`:
  ``can.Bus(interface="dobhil", channel="demo")`` is a bus with the emulated drive and
  plant of a config behind it, in real time.

:mod:`~dobhil.canio.canlog` converts CAN logs in python-can's formats to and from
recordings (``dobhil log export --can``, ``dobhil log import``).
:mod:`~dobhil.canio.frames` names the frame topics; the frame codec is recording's (``schemas``).
Nothing is imported here, so python-can loads only the plugin it asks for.
"""
