"""training layer of byoc-cli."""
