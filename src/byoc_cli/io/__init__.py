"""io layer of byoc-cli."""
