"""The motion layer: trajectory planning (ruckig), the PLCopen axis state machine, and the
per-axis steppers whose targets the cycle writes (see docs/motion.md)."""
