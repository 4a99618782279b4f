"""evaluation layer of byoc-cli."""
