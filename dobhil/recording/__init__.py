"""MCAP recording of dobhil runs: the topic table (``schemas``), the loop side (``runlog``),
the writer process (``process``) and the one writer (``writer``), the one reader
(``reader``), ``recover`` and ``convert``; the layouts (``layouts``: a message per topic or
per cycle, ``cycles``) and ``relayout`` between them; ``docs/recording.md`` has the diagram
and the guarantees. Nothing is imported here: the writer process starts without python-can or numpy.
"""
