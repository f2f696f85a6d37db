"""The ``graffmatch`` command line (typer + rich)."""
