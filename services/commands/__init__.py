"""The ``hydrosoft-stack`` command line: the dispatcher and one module per subcommand that is not a service."""
