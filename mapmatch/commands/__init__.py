"""Subcommands of the ``mapmatch`` CLI, one module each (see ``mapmatch.cli``)."""
