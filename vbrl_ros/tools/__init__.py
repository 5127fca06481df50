"""The ``vbrl`` command: :mod:`.cli` and one module per subcommand, with their shared options."""
