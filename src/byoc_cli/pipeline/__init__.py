"""pipeline layer of byoc-cli."""
