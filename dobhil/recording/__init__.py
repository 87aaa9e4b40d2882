"""MCAP recording of dobhil runs: one write path, one reader, and the tools around them.

    loop thread --tuples--> RunLog (a Batch, runlog) --pickled, one os.write per batch-->
        writer process (process) --> LogWriter (writer) --> mcap.writer.Writer --> run.mcap
        [--> live view]
    run.mcap --> LogFile (reader) --> log info / export / replay / report; recover

- :mod:`~dobhil.recording.schemas`  the one table of topics: fields, JSON schemas, encoders
- :mod:`~dobhil.recording.runlog`   :class:`RunLog`, the runtime's cycle sink and bus tap
- :mod:`~dobhil.recording.process`  the hand-over (Batch) and the writer process
- :mod:`~dobhil.recording.writer`   :class:`LogWriter`, the only code that writes a log
- :mod:`~dobhil.recording.reader`   :class:`LogFile`, checked reading
- :mod:`~dobhil.recording.recover`  salvage a file cut short or damaged
- :mod:`~dobhil.recording.convert`  CSV export, CAN logs out and in via python-can

Nothing is imported here, so the writer process starts without python-can or numpy.
``docs/recording.md`` describes the channels and the guarantees.
"""
