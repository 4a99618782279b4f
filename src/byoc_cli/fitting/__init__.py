"""fitting layer of byoc-cli."""
