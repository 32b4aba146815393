"""Command-line entry points (Hydra apps over the repository's ``conf/``)."""
