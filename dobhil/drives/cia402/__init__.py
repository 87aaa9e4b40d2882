"""CiA 402 servo drives (cyclic synchronous torque) over CANopen, through canopen."""
