"""cli layer of byoc-cli."""
