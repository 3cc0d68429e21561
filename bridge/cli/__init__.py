"""The `hilbo` command line (entry point :func:`bridge.cli.main.main`)."""
