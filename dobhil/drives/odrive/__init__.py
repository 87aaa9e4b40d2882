"""ODrive CAN Simple: :mod:`.codec` (pure, firmware 0.6 default and 0.5) and :mod:`.drive`."""
