"""models layer of byoc-cli."""
