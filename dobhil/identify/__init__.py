"""``dobhil identify``: the plant's numbers (inertia, friction, environment, delay) fitted to
a recorded run, on the emulator's own plant model (:mod:`dobhil.identify.model`, fitted by
:mod:`dobhil.identify.fit` with lmfit); :mod:`dobhil.identify.data` reads the samples from a
log and finds its free-motion and contact segments."""
