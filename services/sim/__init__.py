"""Simulated hardware helpers: bus-backed devices and the simulated world's renderers."""
