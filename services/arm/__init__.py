"""The per-arm pure rules: motion safety, re-approach, a goal's progress, task frame, the stored F/T tare and its
checks."""
