"""Recordings: the MCAP format, the Foxglove scene and the image codec."""
