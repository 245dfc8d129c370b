"""The per-arm pure rules: motion safety, re-approach, task frame, the stored F/T tare and its checks."""
