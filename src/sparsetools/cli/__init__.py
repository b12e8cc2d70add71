"""Command line: thin click commands, one module per subcommand."""
