"""RGB cameras: calibration, the OpenCV driver and a simulated camera that renders AprilTags."""
