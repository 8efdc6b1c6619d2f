"""fieldbus: the CANopen CiA 402 master, Modbus I/O, and simulators of both."""
