"""Monte-Carlo campaigns: many lockstep emulated runs of the whole stack over parameter
distributions, executed as Dask tasks (:mod:`dobhil.cluster`).

- :mod:`~dobhil.campaign.draws`: ``--vary KEY=DIST`` parsed, and each run's draws from
  ``numpy.random.SeedSequence(seed)``'s child ``i`` alone;
- :mod:`~dobhil.campaign.runner`: one run, pure data in and out (what a worker calls);
- :mod:`~dobhil.campaign.campaign`: the plan, its execution on a Dask client, the table,
  its summary and the command that reproduces a run alone.
"""
