"""hydrosoft: differentiable non-holonomic hydroelastic contact models for compliant tactile manipulation."""
