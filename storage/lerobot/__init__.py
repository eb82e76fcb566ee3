"""LeRobotDataset (v3.0) export and import: ``attempts`` (our files as frame tables), ``layout`` (the
writer), ``reader`` (a dataset as MCAP demonstrations)."""
