"""Robotiq FT 300 force/torque sensor: the serial stream protocol, the pyserial driver and a pty simulator."""
