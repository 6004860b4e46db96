"""One library function per subcommand; carto_cli/cli.py only parses arguments, calls one, and prints."""
