"""Services: asyncio processes, bus, launcher and the `hydrosoft-stack` command line."""
