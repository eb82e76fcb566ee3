"""Episodes (MCAP), datasets, and the names shared across packages."""
