"""Soft Bubble depth path: the simulated membrane renderer and deformation-to-penetration (no real depth driver yet)."""
