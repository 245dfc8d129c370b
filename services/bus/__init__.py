"""Process plumbing: typed messages, ZeroMQ sockets, the config, the service runtime and command line."""
