"""The composition root: the only place that builds devices, real or simulated.

The command line's device-driving commands and the demo live here; they may import every
subsystem (``gonio.rig``, ``gonio.capture``, ``gonio.fitting``, ``gonio.simulator``) and
wire them together.  Nothing else imports this package.
"""
