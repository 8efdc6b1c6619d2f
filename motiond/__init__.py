"""motiond: the daemon and the command line that wire the layers together."""
