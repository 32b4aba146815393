"""Physics shared by rendering, losses and tests: one implementation of each concept.

- :mod:`nrt.physics.envmap`: equirectangular environment maps (Mitsuba's convention).
- :mod:`nrt.physics.phase`: Henyey-Greenstein phase function and its sampling.
- :mod:`nrt.physics.volume`: ray-box intersection, grid lookup, transmittance.
"""
