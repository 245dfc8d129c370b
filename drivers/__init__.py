"""Hardware adapters (real and simulated twins). Not built yet: see README "Not built yet"."""
