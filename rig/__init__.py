"""gonio.rig: the Dynamixel servo transport, control table, kinematics and rig device."""
