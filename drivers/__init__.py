"""Hardware adapters: one async interface per device kind (``base``), real drivers and simulated twins side by side."""
