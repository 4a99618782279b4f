"""matching layer of byoc-cli."""
