"""Recording sources, writers and file formats."""
