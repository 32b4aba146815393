"""nrt: volumetric inverse rendering with neural radiative transfer."""

__version__ = "0.1.0"
