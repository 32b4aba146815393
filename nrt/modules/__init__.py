"""Networks (hash grid, fields) and the LightningModules of each stage."""
