"""moteus (mjbots) controllers over CAN FD: :mod:`.codec` (pure: the multiplex register
protocol, its resolutions and arbitration ids), :mod:`.frames` (the frames dobhil sends),
and the drive, its emulated controller, profile rules, preflight and protocol object."""
