"""One module per ``gearbench`` subcommand (see ``gearbench.cli``)."""
