"""Encodings and small networks that fields are built from (hash grid, SIREN, output
activations); they know nothing of media or light."""
