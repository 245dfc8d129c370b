"""Reproducible benchmarks behind ``hydrosoft-stack bench ...``.

Each benchmark module exposes ``add_arguments(parser)`` and ``run(args) -> int`` and imports torch and the
model library only inside ``run``, so building the command line stays fast.
"""
