"""planner: canonical commands in, timed jerk-limited setpoints out (ruckig). No I/O."""
