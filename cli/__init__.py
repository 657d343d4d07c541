"""The camloc command line: thin typer commands that wire options to library calls."""
