"""MIT-mode actuators (Mini-Cheetah firmware, CubeMars AK, Damiao DM-J): :mod:`.codec`
(pure: special frames, command and reply packing in the firmware's arithmetic),
:mod:`.models` (the model table ``drivers/mit-models.yaml``: ranges, reply layouts,
firmware variants), and the drive, its profile rules and its preflight."""
