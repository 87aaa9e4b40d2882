"""Grey-box identification of the servo, its environment and the loop delay from a recorded run
(``dobhil identify``): :mod:`dobhil.identify.data` reads the samples and finds the free-motion
and contact segments; :mod:`dobhil.identify.fit` fits the emulator's exact sampled plant."""
