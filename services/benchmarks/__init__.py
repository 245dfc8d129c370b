"""Benchmarks of the stack (bus latency, tag tracker accuracy) behind `hydrosoft-stack bench ...`."""
