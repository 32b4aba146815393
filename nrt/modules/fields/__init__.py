"""Fields over the medium's box: the EA density, light fields, media, the protocols a stage
checks them against, and the coarse-to-fine schedule of grids."""
