"""NMT command and state names (CiA 301), for logs and the bus dump."""

NMT_COMMANDS = {0x01: "start", 0x02: "stop", 0x80: "enter pre-operational", 0x81: "reset node",
                0x82: "reset communication"}
NMT_STATES = {0x00: "initialising", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
