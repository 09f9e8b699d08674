"""The ``occkit`` commands' arguments and glue, one module per group of commands; :mod:`occkit.cli` dispatches."""
