"""Universal Robots e-Series arm: the ur_rtde driver and a simulated controller that the real client talks to."""
